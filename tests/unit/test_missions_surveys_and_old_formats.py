"""Files users bring that the first readers refused (issue 31): QGC surveys and corridor scans (their stored items),
fence- or rally-only plans, WPL rows out of order, MAVProxy's older rally and fence files, and commands newer than
the installed pymavlink. Each is checked against what pymavlink's own loaders make of the same file."""

import json
import os

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ground import cli
from missions import MissionFileError, load_mission, loads_plan
from missions.files import loads_mission
from missions.model import Frame, MavCmd, MissionType
from missions.validate import validate
from nac_onboard.mavlink.dialect import mission_catalogue
from tests.unit.test_mission_safety import FUZZ_EXAMPLES

os.environ.setdefault("MAVLINK20", "1")  # pymavlink's mission-protocol loaders need MAVLink 2
from pymavlink import mavwp  # noqa: E402


def simple(jump_id, command, frame, params):
    return {"type": "SimpleItem", "autoContinue": True, "doJumpId": jump_id, "command": command, "frame": frame,
            "params": params}


def plan(items, home=(47.3977, 8.5456, 488.0), fence=None, rally=None):
    doc = {"fileType": "Plan", "groundStation": "QGroundControl", "version": 1,
           "mission": {"version": 2, "firmwareType": 3, "vehicleType": 2, "cruiseSpeed": 15, "hoverSpeed": 5,
                       "plannedHomePosition": home, "items": items},
           "geoFence": {"version": 2, "polygons": [], "circles": fence or []},
           "rallyPoints": {"version": 2, "points": rally or []}}
    if home == "missing":
        del doc["mission"]["plannedHomePosition"]
    return json.dumps(doc)


TAKEOFF = simple(1, 22, 3, [0, 0, 0, None, 47.3977, 8.5456, 20])
SURVEY = {"type": "ComplexItem", "complexItemType": "survey", "version": 5, "polygon": [[47.39, 8.54]] * 3,
          "TransectStyleComplexItem": {"Items": [simple(2, 16, 3, [0, 0, 0, None, 47.3979, 8.5460, 20]),
                                                 simple(3, 206, 2, [5, 0, 1, 0, 0, 0, 0]),
                                                 simple(4, 16, 3, [0, 0, 0, None, 47.3979, 8.5450, 20])]}}


def test_a_survey_reads_its_stored_items_in_its_place_and_numbers_on_from_them():
    """As QGC uploads it: takeoff, the survey's three stored items, then what follows; a DO_JUMP naming a stored
    item's doJumpId jumps to its place in the flattened list."""
    jump = simple(5, 177, 2, [3, 1, 0, 0, 0, 0, 0])
    mission = loads_plan(plan([TAKEOFF, SURVEY, jump, simple(6, 20, 2, [0] * 7)]), "survey.plan")
    assert [(it.seq, it.command) for it in mission.items] == [(1, 22), (2, 16), (3, 206), (4, 16), (5, 177),
                                                               (6, 20)]
    assert mission.items[4].p1 == 3.0, "doJumpId 3 is the camera trigger, the third item"
    assert mission.where(MissionType.MISSION, 3) == 'item 2 (ComplexItem "survey") stored item 2 (doJumpId 3)'
    assert mission.notes == ['item 2 (ComplexItem "survey"): its 3 stored items read in its place, as '
                             'QGroundControl uploads them']


def test_a_corridor_scan_reads_as_a_survey_does():
    corridor = dict(SURVEY, complexItemType="CorridorScan")
    assert len(loads_plan(plan([TAKEOFF, corridor])).items) == 4


@pytest.mark.parametrize("home", [None, [None, None, None], "missing"])
def test_a_fence_or_rally_only_plan_has_no_home_to_check(home, tmp_path):
    circle = {"circle": {"center": [47.3977, 8.5456], "radius": 80.0}, "inclusion": True, "version": 1}
    path = tmp_path / "fence.plan"
    path.write_text(plan([], home=home, fence=[circle], rally=[[47.3978, 8.5457, 30.0]]))
    mission = load_mission(path, catalogue=mission_catalogue())
    assert mission.home is None and (len(mission.items), len(mission.fence), len(mission.rally)) == (0, 1, 1)


def test_a_null_home_is_still_refused_where_there_is_a_mission_to_fly(tmp_path):
    path = tmp_path / "nohome.plan"
    path.write_text(plan([TAKEOFF, simple(2, 20, 2, [0] * 7)], home=[None, None, None]))
    with pytest.raises(MissionFileError, match="planned home has a NaN/null coordinate"):
        load_mission(path)


WPL_OUT_OF_ORDER = """QGC WPL 110
0\t1\t0\t16\t0\t0\t0\t0\t-35.3632\t149.1652\t584\t1
1\t0\t3\t22\t0\t0\t0\t0\t0\t0\t20\t1
3\t0\t3\t16\t0\t0\t0\t0\t-35.3640\t149.1660\t20\t1
2\t0\t3\t16\t0\t0\t0\t0\t-35.3630\t149.1650\t20\t1
7\t0\t3\t20\t0\t0\t0\t0\t0\t0\t0\t1
"""


def test_wpl_rows_out_of_order_are_read_in_file_order_and_said_once(tmp_path):
    path = tmp_path / "shuffled.waypoints"
    path.write_text(WPL_OUT_OF_ORDER)
    mission = load_mission(path)
    assert [(it.seq, it.command, it.lat_deg) for it in mission.items] == [
        (1, 22, 0.0), (2, 16, -35.364), (3, 16, -35.363), (4, 20, 0.0)]
    loader = mavwp.MAVWPLoader()
    loader.load(str(path))
    assert [(w.seq, w.command, round(w.x, 4)) for w in loader.wpoints[1:]] == \
        [(it.seq, it.command, it.lat_deg) for it in mission.items], "as pymavlink's loader numbers them"
    assert mission.notes == ["rows renumbered in file order from 0 (line 4 has INDEX 3 where 2 was expected), as "
                             "QGroundControl, MAVProxy and pymavlink read them"]


def test_the_cli_says_the_note_once(tmp_path, capsys):
    path = tmp_path / "shuffled.waypoints"
    path.write_text(WPL_OUT_OF_ORDER)
    assert cli.main(["mission", "validate", str(path)]) == 0
    out = capsys.readouterr().out
    assert out.count("note: rows renumbered") == 1 and ", 4 mission items" in out


RALLY = """# MAVProxy rally save, older format
RALLY -35.362938\t149.165085\t60.000000\t40.000000\t90.000000\t0
RALLY -35.364000\t149.166000\t50.000000\t30.000000\t0.000000\t1
"""
FENCE = """-35.363000\t149.165000
-35.362000\t149.164000
-35.362000\t149.166000
-35.364000\t149.166000
-35.364000\t149.164000
-35.362000\t149.164000
"""


def _mavwp(protocol, path):
    loader = protocol(target_system=1, target_component=1)
    loader.load(str(path))
    return [loader.item(k) for k in range(loader.count())]


def test_mavproxys_old_rally_file_gives_the_rally_points_mavproxy_loads(tmp_path):
    path = tmp_path / "rally.txt"
    path.write_text(RALLY)
    mission = load_mission(path)
    theirs = _mavwp(mavwp.MissionItemProtocol_Rally, path)
    assert [(it.command, it.frame, round(it.lat_deg * 1e7), round(it.lon_deg * 1e7)) for it in mission.rally] == \
        [(w.command, w.frame, w.x, w.y) for w in theirs]
    assert [it.alt_m for it in mission.rally] == [60.0, 50.0] and mission.rally[0].frame == Frame.GLOBAL_RELATIVE_ALT
    assert not mission.items and mission.home is None


def test_mavproxys_old_fence_file_gives_the_fence_mavproxy_loads(tmp_path):
    path = tmp_path / "fence.txt"
    path.write_text(FENCE)
    mission = load_mission(path)
    theirs = _mavwp(mavwp.MissionItemProtocol_Fence, path)
    assert [(it.command, it.frame, it.p1) for it in mission.fence] == [(w.command, w.frame, w.param1) for w in theirs]
    for ours, w in zip(mission.fence, theirs, strict=True):  # mavwp truncates to 1e-7 degrees, NAC rounds
        assert abs(ours.lat_deg * 1e7 - w.x) <= 1 and abs(ours.lon_deg * 1e7 - w.y) <= 1
    assert mission.fence[0].command == MavCmd.NAV_FENCE_RETURN_POINT and len(mission.fence) == 5
    assert "its closing point, line 6, dropped" in mission.notes[0]


@pytest.mark.parametrize("suffix", [".waypoints", ".plan"])
def test_old_rally_and_fence_files_convert_to_files_qgc_reads(suffix, tmp_path, capsys):
    for name, text in (("rally.txt", RALLY), ("fence.txt", FENCE)):
        source, target = tmp_path / name, tmp_path / f"{name}{suffix}"
        source.write_text(text)
        assert cli.main(["mission", "convert", str(source), str(target)]) == 0
        back, read = load_mission(target, flight=False), load_mission(source, flight=False)
        if suffix == ".waypoints":
            assert back.same_items_as(read)
        else:  # a .plan keeps the return point apart from the polygon (breachReturn)
            def key(it):
                return it.command, round(it.lat_deg, 6), round(it.lon_deg, 6), it.alt_m
            assert sorted(map(key, back.fence + back.rally)) == sorted(map(key, read.fence + read.rally))
    assert "note: a MAVProxy rally file: 2 rally points" in capsys.readouterr().out


@pytest.mark.parametrize("text, where, reason", [
    ("RALLY -35.36 149.16 60 40 90\n", "line 1", "has 6 fields; expected 7"),
    ("RALLY -35.36 149.16 sixty 40 90 0\n", "line 1", "field 4 is 'sixty'; expected a number"),
    ("RALLY -35.36 149.16 60 40 90 0\nPOINT -35.36 149.16 60 40 90 0\n", "line 2", "expected RALLY"),
    ("-35.36 149.16\n-35.36 149.17\n-35.37 149.17\n-35.36 149.16\n", "line 4", "of 4 points; expected at least 5"),
    ("-35.36 149.16\n-35.36\n", "line 2", "has 1 fields; expected 2"),
])
def test_malformed_old_files_name_the_line(text, where, reason):
    with pytest.raises(MissionFileError) as refused:
        loads_mission(text, "old.txt")
    assert refused.value.where == where and reason in refused.value.reason, str(refused.value)


def test_a_command_newer_than_pymavlink_is_known_by_name_and_an_undefined_number_still_refused(tmp_path):
    """MAV_CMD_ESTIMATOR_SENSOR_ENABLE (43006, development.xml, 2026) is in MAVLink's definitions but not in the
    installed pymavlink's dialect; 43007 is in no dialect."""
    from pymavlink import mavutil
    assert 43006 not in mavutil.mavlink.enums["MAV_CMD"], "pymavlink caught up: pick a newer command"
    assert mission_catalogue().name(43006) == "ESTIMATOR_SENSOR_ENABLE"
    for command, code in ((43006, 0), (43007, 2)):
        path = tmp_path / f"cmd{command}.waypoints"
        path.write_text("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t-35.36\t149.16\t584\t1\n"
                        "1\t0\t3\t22\t0\t0\t0\t0\t0\t0\t20\t1\n"
                        f"2\t0\t2\t{command}\t0\t0\t0\t0\t0\t0\t0\t1\n")
        assert cli.main(["mission", "validate", "--firmware", "any", str(path)]) == code


FUZZ_BASES = [plan([TAKEOFF, SURVEY, simple(5, 20, 2, [0] * 7)]), plan([], home=None, rally=[[47.39, 8.54, 30.0]]),
              WPL_OUT_OF_ORDER, RALLY, FENCE]


@settings(max_examples=FUZZ_EXAMPLES, deadline=None)
@given(st.sampled_from(FUZZ_BASES).flatmap(lambda base: st.tuples(
    st.just(base), st.integers(0, len(base)), st.integers(0, len(base) - 1), st.text(max_size=6))))
def test_truncated_or_flipped_new_formats_are_read_or_refused_never_a_traceback(case):
    """Each new reader's input cut short, and with a few characters changed: read (and validated) or refused with
    the file's name first, never another exception."""
    base, cut, at, junk = case
    for text in (base[:cut], base[:at] + junk + base[at + len(junk):]):
        try:
            validate(loads_mission(text, "fuzz"), "fuzz", catalogue=mission_catalogue())
        except MissionFileError as err:
            assert str(err).startswith("fuzz: ")


def test_the_upload_progress_goes_to_the_stderr_of_the_call_not_of_import_time(monkeypatch):
    """Under pytest-xdist, a stderr bound when the module was imported had been closed by a later upload (a CI
    run's survey upload failed on it)."""
    import io
    import sys

    from ground.operator.commands import TransferProgress

    now = io.StringIO()
    monkeypatch.setattr(sys, "stderr", now)
    TransferProgress("mission")(3, 3)
    assert now.getvalue() == "\rmission [" + "#" * 30 + "] 3/3\n"
