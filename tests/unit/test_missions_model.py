"""Mission model: the wire form ArduPilot expects (item 0 = home) and the validation rules."""

import math

import pytest

from missions import Frame, MavCmd, Mission, MissionFileError, MissionItem, MissionType, PlannedHome, validate

HOME = PlannedHome(47.397742, 8.545594, 488.0)


def flyable(*middle: MissionItem) -> Mission:
    items = [MissionItem(1, MavCmd.NAV_TAKEOFF, Frame.GLOBAL_RELATIVE_ALT, alt_m=10.0)]
    items += [MissionItem(k, it.command, it.frame, it.p1, it.p2, it.p3, it.p4, it.lat_deg, it.lon_deg, it.alt_m)
              for k, it in enumerate(middle, 2)]
    items.append(MissionItem(len(items) + 1, MavCmd.NAV_LAND, Frame.GLOBAL_RELATIVE_ALT))
    return Mission(home=HOME, items=items)


def wp(lat_deg=47.398, lon_deg=8.546, alt_m=10.0, frame=Frame.GLOBAL_RELATIVE_ALT, command=MavCmd.NAV_WAYPOINT,
       p1=0.0, p2=0.0):
    return MissionItem(0, command, frame, p1, p2, lat_deg=lat_deg, lon_deg=lon_deg, alt_m=alt_m)


def problem(mission: Mission) -> str:
    with pytest.raises(MissionFileError) as caught:
        validate(mission, "m.plan")
    return str(caught.value)


def test_to_wire_puts_planned_home_in_slot_zero():
    mission = flyable(wp())
    wire = mission.to_wire()
    assert [it.seq for it in wire] == [0, 1, 2, 3]
    home = wire[0]
    assert (home.command, home.frame, home.lat_deg, home.lon_deg, home.alt_m) == (
        MavCmd.NAV_WAYPOINT, Frame.GLOBAL, HOME.lat_deg, HOME.lon_deg, HOME.alt_m)
    assert wire[1:] == mission.items


def test_to_wire_without_home_sends_zeros_and_from_wire_reads_none():
    mission = Mission(items=[MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=5.0)])
    wire = mission.to_wire()
    assert (wire[0].lat_deg, wire[0].lon_deg, wire[0].alt_m) == (0.0, 0.0, 0.0)
    assert Mission.from_wire(wire).home is None


def test_from_wire_is_the_inverse_of_to_wire():
    fence = [MissionItem(0, MavCmd.NAV_FENCE_CIRCLE_INCLUSION, Frame.GLOBAL, 100.0, lat_deg=47.39, lon_deg=8.54,
                         mission_type=MissionType.FENCE)]
    mission = flyable(wp(), wp(command=MavCmd.DO_CHANGE_SPEED, frame=Frame.MISSION, lat_deg=0, lon_deg=0, p1=1,
                             p2=3.0))
    mission.fence = fence
    back = Mission.from_wire(mission.to_wire(), fence=fence)
    assert back.home == HOME and back.same_items_as(mission) and back.same_as(mission)
    assert Mission.from_wire([]).items == []


def test_same_items_as_allows_wire_rounding_but_not_changes():
    mission = flyable(wp())
    rounded = Mission.from_wire([MissionItem(it.seq, it.command, it.frame, it.p1, it.p2, it.p3, it.p4,
                                             round(it.lat_deg * 1e7) / 1e7 + 4e-8, it.lon_deg, it.alt_m)
                                 for it in mission.to_wire()])
    assert rounded.same_items_as(mission)
    moved = flyable(wp(lat_deg=47.3981))
    assert not moved.same_items_as(mission)
    assert not flyable().same_items_as(mission)


def test_to_wire_refuses_misnumbered_items():
    with pytest.raises(ValueError, match="numbered 1..2"):
        Mission(items=[MissionItem(1, 22), MissionItem(5, 21)]).to_wire()


def test_valid_mission_passes_and_zero_position_means_here():
    validate(flyable(wp(), wp(lat_deg=0.0, lon_deg=0.0), wp(command=MavCmd.NAV_RETURN_TO_LAUNCH, lat_deg=0,
                                                            lon_deg=0, alt_m=0)), "m.plan")
    validate(flyable(wp(lat_deg=-90.0, lon_deg=180.0, alt_m=-100.0)), "m.plan")
    validate(flyable(wp(frame=Frame.GLOBAL_INT, alt_m=-500.0)), "m.plan")
    validate(flyable(wp(frame=Frame.GLOBAL_TERRAIN_ALT, alt_m=30.0)), "m.plan")


@pytest.mark.parametrize(("item", "expected"), [
    (wp(lat_deg=95.0), "m.plan: item 2: latitude 95.0 is outside -90..90"),
    (wp(lon_deg=-181.0), "m.plan: item 2: longitude -181.0 is outside -180..180"),
    (wp(lat_deg=math.nan), "m.plan: item 2: latitude is NaN/null"),
    (wp(alt_m=math.nan), "m.plan: item 2: altitude is NaN/null"),
    (wp(alt_m=-101.0), "altitude -101.0 m is outside -100..10000 m (above home/terrain"),
    (wp(frame=Frame.GLOBAL, alt_m=-501.0), "altitude -501.0 m is outside -500..10000 m (AMSL"),
    (wp(frame=Frame.GLOBAL, alt_m=10001.0), "outside -500..10000 m"),
    (wp(frame=Frame.MISSION), "frame 2 (MISSION), which is not flown here"),
    (wp(frame=Frame.LOCAL_ENU), "frame 4 (LOCAL_ENU), which is not flown here"),
    (wp(command=MavCmd.NAV_LOITER_TURNS + 1000), "unknown command 1018"),
    (wp(command=MavCmd.NAV_RALLY_POINT), "NAV_RALLY_POINT (5100) is a fence/rally command"),
    (wp(command=MavCmd.DO_JUMP, frame=Frame.MISSION, p1=7, p2=1), "DO_JUMP target item 7 does not exist; "
                                                                   "expected an item number 1..3"),
    (wp(command=MavCmd.DO_JUMP, frame=Frame.MISSION, p1=math.nan), "DO_JUMP target (param1) is NaN"),
    (wp(command=MavCmd.DO_JUMP, frame=Frame.MISSION, p1=1, p2=-2), "repeat count (param2) is -2.0"),
    (wp(command=MavCmd.DO_CHANGE_SPEED, frame=Frame.MISSION, p1=1, p2=math.nan), "DO_CHANGE_SPEED speed"),
])
def test_bad_item_is_named_with_the_reason(item, expected):
    assert expected in problem(flyable(item))


def test_do_jump_and_do_commands_accept_mission_frame():
    validate(flyable(wp(), wp(command=MavCmd.DO_JUMP, frame=Frame.MISSION, lat_deg=0, lon_deg=0, p1=2, p2=-1),
                     wp(command=MavCmd.DO_CHANGE_SPEED, frame=Frame.MISSION, lat_deg=0, lon_deg=0, p1=1, p2=0.67)),
             "m.plan")


def test_mission_level_problems():
    assert problem(Mission(home=HOME)) == ("m.plan: mission: is empty (no mission items); expected at least one "
                                           "(a flyable mission starts with NAV_TAKEOFF and ends with NAV_LAND or RTL)")
    gap = flyable(wp())
    gap.items[1] = MissionItem(3, MavCmd.NAV_WAYPOINT, lat_deg=47.4, lon_deg=8.5, alt_m=10)
    assert "has sequence number 3 where 2 was expected" in problem(gap)
    far_home = flyable(wp())
    far_home.home = PlannedHome(47.0, 200.0, 488.0)
    assert problem(far_home) == "m.plan: planned home: home longitude 200.0 is outside -180..180"


def test_fence_and_rally_rules():
    def fence_item(seq, command, p1, lat=47.39, lon=8.54):
        return MissionItem(seq, command, Frame.GLOBAL, p1, lat_deg=lat, lon_deg=lon, mission_type=MissionType.FENCE)

    mission = flyable(wp())
    mission.fence = [fence_item(k, MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION, 3, 47.39 + k * 1e-3) for k in range(3)]
    mission.rally = [MissionItem(0, MavCmd.NAV_RALLY_POINT, Frame.GLOBAL_RELATIVE_ALT, lat_deg=47.4, lon_deg=8.5,
                                 alt_m=20, mission_type=MissionType.RALLY)]
    validate(mission, "m.plan")
    mission.fence = mission.fence[:2]
    assert "polygon announces 3 vertices but the fence ends after 2" in problem(mission)
    mission.fence = [fence_item(0, MavCmd.NAV_FENCE_CIRCLE_EXCLUSION, -5)]
    assert problem(mission) == "m.plan: fence item 0: fence circle radius (param1) is -5.0; expected metres > 0"
    mission.fence = [fence_item(0, MavCmd.NAV_FENCE_CIRCLE_INCLUSION, 50, lat=0, lon=0)]
    assert "at latitude 0, longitude 0" in problem(mission)
    mission.fence = [fence_item(0, MavCmd.NAV_WAYPOINT, 0)]
    assert "in the fence; expected a fence command" in problem(mission)
    mission.fence = []
    mission.rally = [MissionItem(0, MavCmd.NAV_WAYPOINT, mission_type=MissionType.RALLY)]
    assert problem(mission).startswith("m.plan: rally item 0: NAV_WAYPOINT (16) in the rally points")


def test_error_carries_source_where_reason():
    err = MissionFileError("a.plan", "item 2 (doJumpId 2)", "latitude 95.0 is outside -90..90")
    assert isinstance(err, ValueError)
    assert (err.source, err.where, err.reason) == ("a.plan", "item 2 (doJumpId 2)", "latitude 95.0 is outside -90..90")
    assert str(err) == "a.plan: item 2 (doJumpId 2): latitude 95.0 is outside -90..90"
    assert str(MissionFileError("a.plan", "", "cannot read")) == "a.plan: cannot read"


def test_the_command_catalogue_is_an_argument_not_an_import_side_effect():
    """Commands beyond missions.model's are the caller's catalogue's: importing the MAVLink adapter registers
    nothing, so a mission validates the same whatever was imported before."""
    from missions.dialect import MODEL_CATALOGUE, CommandCatalogue, DialectCommand
    from nac_onboard.mavlink.dialect import mission_catalogue

    aux = flyable(wp(command=218, frame=Frame.MISSION, lat_deg=0.0, lon_deg=0.0, p1=1.0))  # DO_AUX_FUNCTION
    assert "unknown command 218: neither MAVLink's common nor its ardupilotmega dialect" in problem(aux)
    validate(aux, "m.plan", catalogue=mission_catalogue())
    assert mission_catalogue().name(218) == "DO_AUX_FUNCTION" and MODEL_CATALOGUE.name(218) == "command 218"
    assert mission_catalogue().name(16) == MODEL_CATALOGUE.name(16) == "NAV_WAYPOINT"

    mine = CommandCatalogue({4321: DialectCommand("NAV_TEST", has_location=True)})
    with pytest.raises(MissionFileError, match="item 2: latitude 95.0 is outside -90..90"):
        validate(flyable(wp(command=4321, lat_deg=95.0)), "m.plan", catalogue=mine)
    with pytest.raises(MissionFileError, match=r"NAV_TEST has frame 2 \(MISSION\), which is not flown here"):
        validate(flyable(wp(command=4321, frame=Frame.MISSION)), "m.plan", catalogue=mine)
    with pytest.raises(TypeError):
        mine.commands[1] = DialectCommand("X", False)  # a catalogue is read-only once made
