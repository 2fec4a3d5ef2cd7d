"""QGC .plan and QGC WPL 110 files: lossless round trips, format conversion, examples, and malformed files."""

import json
import math
import random
from pathlib import Path

import pytest

from missions import (
    Frame,
    MavCmd,
    Mission,
    MissionFileError,
    MissionItem,
    MissionType,
    PlannedHome,
    dumps_plan,
    dumps_wpl,
    load_mission,
    loads_mission,
    loads_plan,
    loads_wpl,
    read_plan,
    read_wpl,
    save_mission,
    validate,
    write_plan,
    write_wpl,
)
from missions.examples import generate
from missions.geo import distance_m

EXAMPLES = Path(__file__).resolve().parents[2] / "missions" / "examples"


def simple(jump_id, command, frame, params, **extra):
    item = {"autoContinue": True, "command": command, "doJumpId": jump_id, "frame": frame, "params": params,
            "type": "SimpleItem"}
    item.update(extra)
    return item


def alt_keys(alt_m, mode=1):
    return {"AMSLAltAboveTerrain": None, "Altitude": alt_m, "AltitudeMode": mode}


# As QGroundControl 4.x writes a plan: altitude keys on position items, none on DO_ items, NaN yaw as null.
QGC_ITEMS = [
    simple(1, 22, 3, [0, 0, 0, None, 47.3977419, 8.5455938, 15], **alt_keys(15)),
    simple(2, 178, 2, [1, 2.5, -1, 0, 0, 0, 0]),
    simple(3, 16, 3, [0, 0, 0, None, 47.39801234567, 8.54612345678, 20.5], **alt_keys(20.5)),
    simple(4, 19, 3, [12.5, 0, 0, None, 47.398, 8.546, 20.5], **alt_keys(20.5)),
    simple(5, 177, 2, [3, 2, 0, 0, 0, 0, 0]),
    simple(6, 16, 0, [0, 0, 0, None, 47.3979, 8.5458, 508.25], **alt_keys(508.25, 2)),
    simple(7, 21, 3, [0, 0, 0, None, 0, 0, 0], **alt_keys(0)),
]
QGC_PLAN = {
    "fileType": "Plan",
    "geoFence": {
        "breachReturn": [47.3978, 8.5457, 30],
        "circles": [{"circle": {"center": [47.3977, 8.5456], "radius": 250.5}, "inclusion": True, "version": 1},
                    {"circle": {"center": [47.3985, 8.5465], "radius": 12}, "inclusion": False, "version": 1}],
        "polygons": [
            {"inclusion": True, "polygon": [[47.396, 8.544], [47.396, 8.547], [47.399, 8.547], [47.399, 8.544]],
             "version": 1},
            {"inclusion": False, "polygon": [[47.3981, 8.5451], [47.3982, 8.5452], [47.3981, 8.5453]],
             "version": 1},
        ],
        "version": 2,
    },
    "groundStation": "QGroundControl",
    "mission": {"cruiseSpeed": 15, "firmwareType": 3, "globalPlanAltitudeMode": 1, "hoverSpeed": 5,
                "items": QGC_ITEMS, "plannedHomePosition": [47.397742, 8.545594, 488], "vehicleType": 2,
                "version": 2},
    "rallyPoints": {"points": [[47.3975, 8.5450, 25], [47.3990, 8.5470, 30.5]], "version": 2},
    "version": 1,
}
QGC_PLAN_TEXT = json.dumps(QGC_PLAN, indent=4)

WPL_TEXT = "\n".join([
    "QGC WPL 110",
    "0\t1\t0\t16\t0\t0\t0\t0\t47.397742\t8.545594\t488.0\t1",
    "1\t0\t3\t22\t0.0\t0.0\t0.0\tnan\t47.3977421234567\t8.5455938765432\t10.0\t1",
    "2\t1\t2\t178\t1\t0.67\t-1\t0\t0\t0\t0\t1",
    "3\t0\t6\t16\t2.5\t0.1\t0\tNaN\t-33.123456789012\t-151.98765432109\t12.345678\t0",
    "4\t0\t2\t177\t3\t-1\t0\t0\t0\t0\t0\t1",
    "5\t0\t3\t21\t0\t0\t0\t0\t0\t0\t0\t1",
    "",
])


def test_plan_round_trip_is_lossless_and_stable():
    first = loads_plan(QGC_PLAN_TEXT, "qgc.plan")
    text = dumps_plan(first)
    second = loads_plan(text, "again.plan")
    assert first.same_as(second)
    assert dumps_plan(second) == text
    assert json.loads(text)["mission"]["items"] == QGC_ITEMS  # every SimpleItem field as QGC wrote it
    assert json.loads(text)["geoFence"] == QGC_PLAN["geoFence"]
    assert json.loads(text)["rallyPoints"] == QGC_PLAN["rallyPoints"]
    assert second.plan.ground_station == "QGroundControl" and second.plan.global_plan_altitude_mode == 1


def test_plan_reads_into_wire_semantics():
    m = loads_plan(QGC_PLAN_TEXT, "qgc.plan")
    assert m.home == PlannedHome(47.397742, 8.545594, 488.0)
    assert [it.seq for it in m.items] == [1, 2, 3, 4, 5, 6, 7]
    assert m.items[2].lat_deg == 47.39801234567 and m.items[2].lon_deg == 8.54612345678
    assert math.isnan(m.items[0].p4) and m.items[4].p1 == 3.0 and m.items[4].p2 == 2.0
    fence = [(it.seq, it.command, it.p1) for it in m.fence]
    assert fence == [(0, 5001, 4), (1, 5001, 4), (2, 5001, 4), (3, 5001, 4), (4, 5002, 3), (5, 5002, 3),
                     (6, 5002, 3), (7, 5003, 250.5), (8, 5004, 12), (9, 5000, 0)]
    assert all(it.mission_type == MissionType.FENCE for it in m.fence)
    assert [(it.command, it.lat_deg, it.alt_m) for it in m.rally] == [(5100, 47.3975, 25), (5100, 47.399, 30.5)]
    validate(m, "qgc.plan")


def test_wpl_round_trip_is_lossless_and_stable():
    first = loads_wpl(WPL_TEXT, "a.waypoints")
    text = dumps_wpl(first)
    second = loads_wpl(text, "b.waypoints")
    assert first.same_as(second)
    assert dumps_wpl(second) == text
    assert text.splitlines()[0] == "QGC WPL 110"
    assert all(len(line.split("\t")) == 12 for line in text.splitlines()[1:])
    item = second.items[2]
    assert (item.lat_deg, item.lon_deg, item.alt_m) == (-33.123456789012, -151.98765432109, 12.345678)
    assert (item.p1, item.p2, item.autocontinue, item.frame) == (2.5, 0.1, False, Frame.GLOBAL_RELATIVE_ALT_INT)
    assert second.items[1].current and not second.items[0].current
    assert math.isnan(second.items[0].p4) and math.isnan(item.p4)
    assert second.home == PlannedHome(47.397742, 8.545594, 488.0)


def test_plan_to_wpl_to_model_keeps_every_item_exactly():
    plan = loads_plan(QGC_PLAN_TEXT, "qgc.plan")
    plan.fence, plan.rally = [], []  # WPL has no place for them
    back = loads_wpl(dumps_wpl(plan), "x.waypoints")
    assert back.same_items_as(plan)
    assert back.home == plan.home
    assert Mission(home=plan.home, items=plan.items).same_as(Mission(home=back.home, items=back.items))


def test_wpl_to_plan_to_model_keeps_every_item():
    wpl = loads_wpl(WPL_TEXT, "a.waypoints")
    back = loads_plan(dumps_plan(wpl), "a.plan")
    assert back.same_items_as(wpl) and back.home == wpl.home
    jump = json.loads(dumps_plan(wpl))["mission"]["items"][3]
    assert jump["command"] == 177 and jump["params"][0] == 3 and jump["doJumpId"] == 4


def test_wpl_refuses_to_drop_fence_and_rally():
    with pytest.raises(MissionFileError, match="2 rally points"):
        dumps_wpl(loads_plan(QGC_PLAN_TEXT, "qgc.plan"), "out.waypoints")


def test_do_jump_targets_translate_between_jump_ids_and_seq():
    items = [simple(10, 22, 3, [0, 0, 0, None, 0, 0, 10]), simple(20, 16, 3, [0, 0, 0, None, 47.4, 8.5, 10]),
             simple(30, 177, 2, [20, 1, 0, 0, 0, 0, 0]), simple(40, 21, 3, [0, 0, 0, None, 0, 0, 0])]
    doc = dict(QGC_PLAN, mission=dict(QGC_PLAN["mission"], items=items))
    m = loads_plan(json.dumps(doc), "ids.plan")
    assert m.items[2].p1 == 2.0  # on the wire DO_JUMP names the sequence number
    assert m.where(MissionType.MISSION, 3) == "item 3 (doJumpId 30)"
    out = json.loads(dumps_plan(m))["mission"]["items"]
    assert [it["doJumpId"] for it in out] == [10, 20, 30, 40] and out[2]["params"][0] == 20


def test_edited_altitude_rederives_qgc_altitude_keys():
    m = loads_plan(QGC_PLAN_TEXT, "qgc.plan")
    m.items[2] = MissionItem(3, 16, 3, lat_deg=47.398, lon_deg=8.546, alt_m=33.0)
    item = json.loads(dumps_plan(m))["mission"]["items"][2]
    assert item["Altitude"] == 33 and item["AltitudeMode"] == 1 and item["params"][6] == 33


def test_load_by_content_save_by_extension_and_convert(tmp_path):
    source = tmp_path / "mission.plan"
    source.write_text(QGC_PLAN_TEXT)
    mission = load_mission(source)
    mission.fence, mission.rally = [], []
    for name in ("out.waypoints", "out.txt", "out.plan"):
        save_mission(mission, tmp_path / name)
        assert load_mission(tmp_path / name).same_items_as(mission)
    assert (tmp_path / "out.txt").read_text().startswith("QGC WPL 110\n")
    assert (tmp_path / "out.plan").read_text().startswith("{")
    swapped = tmp_path / "really-a-plan.waypoints"  # content decides the format, not the name
    swapped.write_text((tmp_path / "out.plan").read_text())
    assert load_mission(swapped).same_items_as(mission)
    write_plan(mission, tmp_path / "p.plan")
    write_wpl(mission, tmp_path / "w.waypoints")
    assert read_plan(tmp_path / "p.plan").same_items_as(read_wpl(tmp_path / "w.waypoints"))
    with pytest.raises(MissionFileError, match="expected .plan, .waypoints or .txt"):
        save_mission(mission, tmp_path / "out.json")


def test_plan_fence_from_the_wire_round_trips():
    fence = loads_plan(QGC_PLAN_TEXT, "qgc.plan").fence
    wire = Mission.from_wire([MissionItem(0, 16, 0), MissionItem(1, 22, 3, alt_m=5)], fence=fence)
    back = loads_plan(dumps_plan(wire), "f.plan")
    assert back.same_items_as(wire)


# ---- examples ---------------------------------------------------------------------------------------------------
EXAMPLE_FILES = sorted(p.name for p in EXAMPLES.glob("*.plan"))


def ground_distance_m(home, item) -> float:
    return distance_m(vars(home), {"lat_deg": item.lat_deg, "lon_deg": item.lon_deg, "alt_m": home.alt_m})


def test_examples_are_the_ones_generate_writes():
    written = generate.examples()
    assert sorted(written) == EXAMPLE_FILES and len(EXAMPLE_FILES) == 7
    for name, mission in written.items():
        assert (EXAMPLES / name).read_text() == dumps_plan(mission, name), f"{name}: rerun missions.examples.generate"


def test_generate_writes_valid_files(tmp_path):
    assert sorted(p.name for p in generate.write_examples(tmp_path)) == EXAMPLE_FILES


@pytest.mark.parametrize("name", EXAMPLE_FILES)
def test_example_loads_validates_and_flies_from_its_vehicle_home(name):
    mission = load_mission(EXAMPLES / name)
    validate(mission, name)
    roles = {"master": 0, "worker1": 1, "worker2": 2, "worker3": 3}
    vehicle = roles[name.removesuffix(".plan").split("-")[-1]]
    assert mission.home == generate.vehicle_home(vehicle)
    assert mission.items[0].command == MavCmd.NAV_TAKEOFF and mission.items[-1].command == MavCmd.NAV_LAND
    assert not mission.fence and not mission.rally
    for item in mission.items:
        if item.lat_deg or item.lon_deg:
            assert ground_distance_m(mission.home, item) <= 300.0
    assert name in (EXAMPLES / "README.md").read_text()


def test_flight_test_workers_fly_north_at_067_mps_and_master_holds():
    for worker in ("flight-test-worker1.plan", "flight-test-worker2.plan"):
        m = load_mission(EXAMPLES / worker)
        speed = [it for it in m.items if it.command == MavCmd.DO_CHANGE_SPEED]
        assert [(it.p1, it.p2) for it in speed] == [(1.0, 0.67)]
        nav = [it for it in m.items if it.command == MavCmd.NAV_WAYPOINT]
        assert all(it.alt_m == 3.04 and it.lon_deg == m.home.lon_deg for it in nav)
        assert 35 <= ground_distance_m(m.home, nav[-1]) <= 45
    master = load_mission(EXAMPLES / "flight-test-master.plan")
    hold = [it for it in master.items if it.command == MavCmd.NAV_LOITER_TIME]
    assert len(hold) == 1 and hold[0].p1 == pytest.approx(60) and hold[0].alt_m == 3.04


# ---- malformed files --------------------------------------------------------------------------------------------
def plan_with(items=None, **mission_changes):
    doc = json.loads(QGC_PLAN_TEXT)
    if items is not None:
        doc["mission"]["items"] = items
    doc["mission"].update(mission_changes)
    return json.dumps(doc, indent=4)


def items_with(k, **changes):
    items = json.loads(json.dumps(QGC_ITEMS))
    items[k].update(changes)
    return items


def wpl_with(line_no, text):
    lines = WPL_TEXT.splitlines()
    lines[line_no - 1] = text
    return "\n".join(lines) + "\n"


no_command = json.loads(json.dumps(QGC_ITEMS))
del no_command[1]["command"]
survey = {"type": "ComplexItem", "complexItemType": "survey", "version": 5, "TransectStyleComplexItem": {}}

MALFORMED = {
    "bad JSON": ("bad.plan", QGC_PLAN_TEXT[:200], "line", "not valid JSON"),
    "missing field": ("missing.plan", plan_with(no_command), "item 2 (doJumpId 2)", 'missing field "command"'),
    "missing items": ("noitems.plan", plan_with().replace('"items"', '"itemz"'), "mission", 'missing field "items"'),
    "latitude 95": ("lat.plan", plan_with(items_with(2, params=[0, 0, 0, None, 95, 8.5, 20])),
                    "item 3 (doJumpId 3)", "latitude 95.0 is outside -90..90"),
    "unknown command": ("cmd.plan", plan_with(items_with(3, command=9999)), "item 4 (doJumpId 4)",
                        "unknown command 9999"),
    "survey storing no items": ("survey.plan", plan_with(QGC_ITEMS[:1] + [survey] + QGC_ITEMS[1:]),
                                'item 2 (ComplexItem "survey")', "stores no mission items"),
    "structure scan": ("scan.plan", plan_with(QGC_ITEMS[:1] + [{"type": "ComplexItem", "complexItemType":
                                                                "StructureScan", "version": 3}]),
                       'item 2 (ComplexItem "StructureScan")', "stores no mission items"),
    "stored item malformed": ("stored.plan", plan_with(QGC_ITEMS[:1] + [dict(survey, TransectStyleComplexItem={
        "Items": [QGC_ITEMS[2], {k: v for k, v in QGC_ITEMS[3].items() if k != "frame"}]})]),
        'item 2 (ComplexItem "survey") stored item 2 (doJumpId 4)', 'missing field "frame"'),
    "WPL header": ("header.waypoints", wpl_with(1, "QGC WPL 100"), "line 1", "expected 'QGC WPL 110'"),
    "WPL columns": ("cols.waypoints", wpl_with(3, "1\t0\t3\t22\t0\t0\t0\t0\t47.39\t8.54\t10"), "line 3",
                    "has 11 columns; expected 12"),
    "NaN latitude": ("nan.waypoints", wpl_with(4, "2\t0\t3\t16\t0\t0\t0\t0\tnan\t8.54\t10\t1"), "line 4",
                     "latitude is NaN"),
    "DO_JUMP to missing item (WPL)": ("jump.waypoints", wpl_with(6, "4\t0\t2\t177\t9\t-1\t0\t0\t0\t0\t0\t1"),
                                      "line 6", "DO_JUMP target item 9 does not exist"),
    "DO_JUMP to missing item (plan)": ("jump.plan", plan_with(items_with(4, params=[9, 2, 0, 0, 0, 0, 0])),
                                       "item 5 (doJumpId 5)", "DO_JUMP target doJumpId 9 is not the doJumpId"),
    "empty mission (plan)": ("empty.plan", json.dumps({k: v for k, v in json.loads(plan_with([])).items()
                                                       if k not in ("geoFence", "rallyPoints")}),
                             "mission", "is empty (no mission items)"),
    "empty mission (WPL)": ("empty.waypoints", "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t47.39\t8.54\t488\t1\n",
                            "mission", "is empty (no mission items)"),
    "duplicate doJumpId": ("dup.plan", plan_with(items_with(3, doJumpId=2)), "item 4 (doJumpId 2)",
                           "doJumpId 2 is already used by item 2"),
    "unflown frame": ("frame.plan", plan_with(items_with(2, frame=1)), "item 3 (doJumpId 3)",
                      "frame 1 (LOCAL_NED), which is not flown here"),
    "altitude": ("alt.plan", plan_with(items_with(2, params=[0, 0, 0, None, 47.4, 8.5, 20000])),
                 "item 3 (doJumpId 3)", "altitude 20000.0 m is outside -100..10000 m"),
    "NaN altitude": ("nanalt.plan", plan_with(items_with(0, params=[0, 0, 0, None, 0, 0, None])),
                     "item 1 (doJumpId 1)", "altitude is NaN/null"),
    "repeat -2": ("repeat.plan", plan_with(items_with(4, params=[3, -2, 0, 0, 0, 0, 0])), "item 5 (doJumpId 5)",
                  "repeat count (param2) is -2.0"),
    "params not 7": ("params.plan", plan_with(items_with(1, params=[1, 2, 3])), "item 2 (doJumpId 2)",
                     'field "params" has 3 entries; expected 7'),
    "not a plan": ("file.plan", json.dumps({"fileType": "Mission", "version": 1}), "top level",
                   'fileType is "Mission"; expected "Plan"'),
    "neither format": ("what.txt", "hello\n", "line 1", "expected a QGroundControl .plan"),
    "WPL number": ("num.waypoints", wpl_with(3, "1\t0\t3\t22\t0\t0\t0\tx\t47.39\t8.54\t10\t1"), "line 3",
                   "P4 is 'x'; expected a number"),
    "geofence version": ("fence.plan", json.dumps(dict(QGC_PLAN, geoFence=dict(QGC_PLAN["geoFence"], version=3))),
                         "geoFence", "version is 3; expected 2"),
    "geofence version 1 with shapes": ("fence1.plan", json.dumps(dict(QGC_PLAN, geoFence=dict(QGC_PLAN["geoFence"],
                                                                                          version=1))),
                                       "geoFence", "QGroundControl ignores version 1 geoFence on load"),
    "polygon of 2": ("poly.plan", json.dumps(dict(QGC_PLAN, geoFence=dict(QGC_PLAN["geoFence"], polygons=[
        {"inclusion": True, "polygon": [[47.3, 8.5], [47.31, 8.5]], "version": 1}]))), "geoFence polygon 1",
        "has 2 vertices; expected at least 3"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_file_names_file_item_and_expectation(case, tmp_path):
    name, text, where, reason = MALFORMED[case]
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(MissionFileError) as caught:
        load_mission(path)
    err = caught.value
    assert isinstance(err, ValueError)
    assert err.source == str(path) and err.where.startswith(where) and reason in err.reason, str(err)
    assert str(err) == f"{path}: {err.where}: {err.reason}"


def test_error_message_format():
    mission = loads_plan(plan_with(items_with(3, params=[0, 0, 0, None, 95, 8.5, 20])), "missions/examples/x.plan")
    with pytest.raises(MissionFileError) as caught:
        validate(mission, "missions/examples/x.plan")
    assert str(caught.value) == "missions/examples/x.plan: item 4 (doJumpId 4): latitude 95.0 is outside -90..90"


def test_missing_file_is_a_mission_file_error(tmp_path):
    with pytest.raises(MissionFileError, match="cannot read the file"):
        load_mission(tmp_path / "nope.plan")


@pytest.mark.parametrize("text", [QGC_PLAN_TEXT, WPL_TEXT], ids=["plan", "wpl"])
def test_damaged_files_only_ever_raise_mission_file_error(text):
    rng = random.Random(7)
    variants = [text[:n] for n in range(0, len(text), 7)]
    for _ in range(400):
        chars = list(text)
        for _ in range(rng.randint(1, 4)):
            chars[rng.randrange(len(chars))] = rng.choice('0123456789.-e,:[]{}"nul \t\nax')
        variants.append("".join(chars))
    for variant in variants:
        try:
            validate(loads_mission(variant, "damaged"), "damaged")
        except MissionFileError as err:
            assert err.source == "damaged" and err.reason
