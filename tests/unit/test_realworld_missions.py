"""Mission files other tools wrote (../shared/data/realworld/plan and wpl, see its SOURCES.md): each is either
fit to fly (its items counted) or refused by `mission validate` with the sentence that says why, and every one
converts losslessly to its own format and to the other where that format can hold it."""

import dataclasses
from pathlib import Path

import pytest

from missions import MissionFileError, dumps_plan, dumps_wpl, load_mission, loads_plan, loads_wpl
from nac_onboard.mavlink.dialect import mission_catalogue
from tests.conftest import SHARED_DATA

REALWORLD = SHARED_DATA / "realworld"

#: file -> (mission items, fence items, rally points) when it flies, or the refusal's telling words
OUTCOMES = {
    "plan/gisnav__ksql_airport.plan": (8, 0, 0),
    "plan/mavros__simple.plan": (10, 6, 3),
    "plan/mavsdk-example__qgroundcontrol_sample.plan": (9, 0, 0),  # geoFence/rallyPoints version 1, empty
    "plan/mavsdk__qgroundcontrol_sample.plan": (6, 0, 0),
    "plan/mavsdk__qgroundcontrol_sample_with_survey.plan": (13, 0, 0),  # a survey's 12 stored items in its place
    "plan/mavsdk__triangle.plan": (4, 0, 0),
    "plan/qgc__ArduPilotSITL-ArduCopter.plan": "QGroundControl's altitude mode 3 (calculated above terrain",
    "plan/qgc__OldFileFormat.mission": "NAV_TAKEOFF has frame 2 (MISSION), which is not flown here",
    "plan/qgc__SectionTest.plan": (5, 0, 0),  # items with four params and a coordinate
    "wpl/ardupilot__AVC2013.txt": (8, 0, 0),
    "wpl/ardupilot__KSFO-VTOL.txt": (11, 0, 0),  # NAV_VTOL_TAKEOFF at 0, 0: "here"
    "wpl/ardupilot__copter_parachute_mission.txt": (2, 0, 0),  # DO_PARACHUTE, space separators
    "wpl/ardupilot__items.txt": (27, 0, 0),  # comment lines, NAV_ARC_WAYPOINT, JUMP_TAG / DO_JUMP_TAG...
    "wpl/ardupilot__justhome.txt": "is empty (no mission items)",
    "wpl/droneinterface__titan_shakedown_mission.waypoints": (8, 0, 0),
    "wpl/pymavlink__fence-110.txt": (0, 10, 0),  # a fence file: every row a fence item
    "wpl/qgc__MissionPlanner.waypoints.txt": (14, 0, 0),
}

#: files that fly for MAVLink but hold an item NAC's simulated ArduCopter refuses at upload: `mission validate` says
#: so by default, and passes them with `--firmware any`
REFUSED_BY_THE_COPTER = {
    "plan/gisnav__ksql_airport.plan": "item 1 (doJumpId 1): SET_CAMERA_MODE (530) would be refused at upload",
    "plan/mavsdk__qgroundcontrol_sample_with_survey.plan":
        "item 1 (doJumpId 1): SET_CAMERA_MODE (530) would be refused at upload",
    "wpl/ardupilot__items.txt": "line 26: NAV_LOITER_TO_ALT (31) would be refused at upload",
}
needs_files = pytest.mark.skipif(not REALWORLD.is_dir(), reason=f"{REALWORLD} is absent (see the developers' guide)")


def _files() -> list[str]:
    if not REALWORLD.is_dir():
        return sorted(OUTCOMES)
    return sorted(str(p.relative_to(REALWORLD)) for kind in ("plan", "wpl") for p in (REALWORLD / kind).iterdir())


@needs_files
def test_every_mission_file_in_the_folder_has_a_documented_outcome():
    assert _files() == sorted(OUTCOMES), "a new file in realworld/: give it its outcome here"


@needs_files
@pytest.mark.parametrize("name", sorted(OUTCOMES))
def test_a_real_mission_file_flies_or_is_refused_with_the_reason(name):
    path = REALWORLD / name
    expected = OUTCOMES[name]
    if isinstance(expected, str):
        with pytest.raises(MissionFileError) as refused:
            load_mission(path, catalogue=mission_catalogue())
        assert str(refused.value).startswith(f"{path}: ") and expected in str(refused.value)
        return
    mission = load_mission(path, catalogue=mission_catalogue())
    assert (len(mission.items), len(mission.fence), len(mission.rally)) == expected


@needs_files
@pytest.mark.parametrize("name", sorted(OUTCOMES))
def test_a_real_mission_file_converts_losslessly_both_ways(name):
    mission = load_mission(REALWORLD / name, flight=False)
    as_plan = loads_plan(dumps_plan(mission))
    assert as_plan.same_items_as(_plan_holds(mission)) and as_plan.home == mission.home
    if Path(name).parent.name == "wpl":
        again = loads_wpl(dumps_wpl(mission))
        assert again.same_as(mission), "a WPL file reads back as it was, the CURRENT flags included"
    if not (mission.items and (mission.fence or mission.rally)):  # WPL holds one list per file
        via_wpl = loads_wpl(dumps_wpl(as_plan))
        assert via_wpl.same_items_as(_plan_holds(mission)) and via_wpl.home == mission.home


def _plan_holds(mission):
    """What a .plan keeps of a mission: its geoFence and rallyPoints have no autocontinue (fence and rally items
    are not flown in sequence, so the flag means nothing there)."""
    return dataclasses.replace(mission, fence=[dataclasses.replace(i, autocontinue=True) for i in mission.fence],
                               rally=[dataclasses.replace(i, autocontinue=True) for i in mission.rally])


@needs_files
@pytest.mark.parametrize("name", sorted(OUTCOMES))
def test_the_cli_validates_and_converts_every_real_mission_file_with_exit_0_or_2_and_no_traceback(
        name, tmp_path, capsys):
    from ground import cli

    path = REALWORLD / name
    refused = isinstance(OUTCOMES[name], str)
    by_the_copter = REFUSED_BY_THE_COPTER.get(name)
    assert cli.main(["mission", "validate", str(path)]) == (2 if refused or by_the_copter else 0)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err
    if refused or by_the_copter:
        assert str(path) in err and (by_the_copter or OUTCOMES[name]) in err, err
    assert cli.main(["mission", "validate", "--firmware", "any", str(path)]) == (2 if refused else 0)
    capsys.readouterr()
    target = tmp_path / ("converted.waypoints" if path.suffix in (".plan", ".mission") else "converted.plan")
    expected = OUTCOMES[name]
    # a WPL file holds one list, so not a mission with its fence and rally
    converts = not (target.suffix == ".waypoints" and isinstance(expected, tuple) and expected[0] and any(expected[1:]))
    assert cli.main(["mission", "convert", str(path), str(target)]) == (0 if converts else 2)
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err and target.exists() == converts
