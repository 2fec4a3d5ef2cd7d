"""Mission files from anywhere: what MAVLink cannot carry is refused before anything is sent, and no file, however
malformed, gets anything but MissionFileError (exit 2) naming the file and the item or line."""

import json
import math
from dataclasses import replace

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from missions import MissionFileError, loads_plan, loads_wpl, validate
from missions.model import Frame, MavCmd, Mission, MissionItem, PlannedHome
from nac_onboard.mavlink.mission_transfer import _e7

FUZZ_EXAMPLES = 300
HOME = PlannedHome(47.39, 8.54, 488.0)


def mission(*extra: MissionItem, count: int | None = None) -> Mission:
    items = [MissionItem(1, MavCmd.NAV_TAKEOFF, Frame.GLOBAL_RELATIVE_ALT, lat_deg=47.39, lon_deg=8.54, alt_m=10)]
    items += [replace(e, seq=len(items) + 1 + k) for k, e in enumerate(extra)]
    if count:
        items += [MissionItem(k, MavCmd.NAV_WAYPOINT, Frame.GLOBAL_RELATIVE_ALT, lat_deg=47.39, lon_deg=8.54,
                              alt_m=10) for k in range(len(items) + 1, count + 1)]
    return Mission(home=HOME, items=items)


@pytest.mark.parametrize("item, message", [
    (MissionItem(0, MavCmd.NAV_WAYPOINT, Frame.GLOBAL_RELATIVE_ALT, p1=1e39, lat_deg=47.4, lon_deg=8.5, alt_m=10),
     "param1 is 1e+39; MAVLink carries it as a 32-bit float"),
    (MissionItem(0, MavCmd.DO_JUMP, Frame.MISSION, p1=1, p2=1, lat_deg=1e10),
     "latitude (param5) is 1e+10; MAVLink carries it as a 32-bit integer"),
    (MissionItem(0, MavCmd.NAV_WAYPOINT, Frame.GLOBAL_RELATIVE_ALT, lat_deg=47.4, lon_deg=8.5, alt_m=math.inf),
     "altitude (param7) is inf"),
])
def test_values_that_do_not_fit_the_wire_are_refused_naming_the_item(item, message):
    with pytest.raises(MissionFileError) as err:
        validate(mission(item), "m.plan")
    assert str(err.value).startswith("m.plan: item 2") and message in str(err.value)


def test_a_command_without_a_position_may_leave_it_unset_and_goes_out_as_zero():
    speed = MissionItem(0, MavCmd.DO_CHANGE_SPEED, Frame.MISSION, p1=1, p2=3, p3=-1, lat_deg=math.nan,
                        lon_deg=math.nan, alt_m=math.nan)
    validate(mission(speed), "m.plan")  # QGC writes null params 5-7: it once crashed the upload midway
    assert _e7(math.nan) == 0 and _e7(47.3977419) == 473977419


def test_more_items_than_a_16_bit_count_are_refused():
    with pytest.raises(MissionFileError, match="at most 65534"):
        validate(mission(count=70_001), "big.plan")


def plan_text(params) -> str:
    item = {"type": "SimpleItem", "command": 16, "frame": 3, "params": params, "autoContinue": True,
            "doJumpId": 1, "AltitudeMode": 1, "Altitude": 10, "AMSLAltAboveTerrain": None}
    return json.dumps({"fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
                       "mission": {"version": 2, "firmwareType": 3, "vehicleType": 2, "cruiseSpeed": 5,
                                   "hoverSpeed": 5, "plannedHomePosition": [47.39, 8.54, 488], "items": [item]},
                       "geoFence": {"version": 2, "polygons": [], "circles": []},
                       "rallyPoints": {"version": 2, "points": []}})


@pytest.mark.parametrize("text, message", [
    (plan_text([0, 0, 0, 0, 47.39, 8.54, 10]).replace("47.39, 8.54, 10]", "47.39, 8.54, 1" + "0" * 400 + "]"),
     "too large for a double"),
    (plan_text([0, 0, 0, 0, 47.39, 8.54, 10]).replace("47.39, 8.54, 10]", "47.39, 8.54, 1" + "0" * 5000 + "]"),
     "not valid JSON"),
    ("[" * 100_000, "nested deeper"),
    (plan_text([0, 0, 0, 0, 47.39, 8.54, 10]).replace("47.39, 8.54, 10]", "47.39, 8.54, Infinity]"),
     "Infinity is not a JSON number"),
])
def test_plans_that_raised_tracebacks_are_refused_by_name(text, message):
    with pytest.raises(MissionFileError) as err:
        loads_plan(text, "bad.plan")
    assert str(err.value).startswith("bad.plan: ") and message in str(err.value)


WPL = "QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t47.39\t8.54\t488\t1\n{row}\n"


@pytest.mark.parametrize("row, message", [
    ("1\t0\t3\t16\t0\t0\t0\t0\t٤٧.٣٩\t8.54\t10\t1", "LAT is '٤٧.٣٩'; expected a number"),  # Arabic-Indic
    ("1\t0\t3\t16\t0\t0\t0\t0\t４７.39\t8.54\t10\t1", "LAT is '４７.39'; expected a number"),  # full-width
    ("1\u00a00\t3\t16\t0\t0\t0\t0\t47.39\t8.54\t10\t1", "has 11 columns"),  # NBSP is no separator
    ("1\t0\t3\t16\t0\t0\t0\t0\t47.39\t8.54\t1_0\t1", "ALT is '1_0'; expected a number"),
])
def test_wpl_numbers_and_separators_are_the_ones_tools_write(row, message):
    with pytest.raises(MissionFileError) as err:
        loads_wpl(WPL.format(row=row), "m.waypoints")
    assert str(err.value).startswith("m.waypoints: line 3") and message in str(err.value)


def test_vertical_tab_and_form_feed_do_not_shift_line_numbers():
    text = ("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t47.39\t8.54\t488\t1\x0b\x0c\n"
            "1\t0\t3\t16\tx\t0\t0\t0\t47.39\t8.54\t10\t1\n")
    with pytest.raises(MissionFileError) as err:
        loads_wpl(text, "m.waypoints")
    assert "line 2" in str(err.value), "the stray control characters are on line 2 and make it malformed"


@settings(max_examples=FUZZ_EXAMPLES, deadline=None)
@given(st.text(max_size=400) | st.sampled_from([plan_text([0, 0, 0, 0, 47.39, 8.54, 10])]).flatmap(
    lambda base: st.integers(0, len(base) - 1).flatmap(
        lambda at: st.text(max_size=12).map(lambda junk: base[:at] + junk + base[at + len(junk):]))))
def test_fuzzed_mission_files_are_read_or_refused_never_a_traceback(text):
    for loads in (loads_plan, loads_wpl):
        try:
            read = loads(text, "fuzz")
            validate(read, "fuzz")
        except MissionFileError as err:
            assert str(err).startswith("fuzz: ")

