"""Parameter storage as ArduPilot keeps a ground station's PARAM_SET, and the strict path for files."""

import math

import pytest

from sitl.vehicle.params import ParamError, ParamTable


def test_a_ground_stations_value_out_of_range_is_kept_and_the_vehicle_acts_within_range():
    table = ParamTable(2)
    note = table.store(0, "WPNAV_SPEED", 3000.0)
    assert note == "WPNAV_SPEED 3000 outside 20..2000: using 2000"
    assert table.reported(0, "WPNAV_SPEED") == 3000.0 and table.get(0, "WPNAV_SPEED") == 2000.0
    assert table.reported(1, "WPNAV_SPEED") == 500.0, "the other vehicle keeps its own value"
    assert table.store(0, "WPNAV_SPEED", 700.0) is None
    assert table.reported(0, "WPNAV_SPEED") == table.get(0, "WPNAV_SPEED") == 700.0


def test_integer_parameters_are_rounded_into_their_storage_type():
    table = ParamTable(1)
    table.store(0, "DISARM_DELAY", 300.0)  # INT8
    assert table.reported(0, "DISARM_DELAY") == 127.0 and table.get(0, "DISARM_DELAY") == 127.0
    table.store(0, "RTL_ALT", 2499.6)  # INT32
    assert table.reported(0, "RTL_ALT") == 2500.0
    table.store(0, "LAND_SPEED", -40000.0)  # INT16: held at its minimum, flown at the range's
    assert table.reported(0, "LAND_SPEED") == -32768.0 and table.get(0, "LAND_SPEED") == 30.0


@pytest.mark.parametrize(("name", "value", "reason"), [
    ("SIM_SPEEDUP", 4.0, "Param write denied (SIM_SPEEDUP)"),
    ("NO_SUCH", 1.0, "unknown parameter 'NO_SUCH'"),
    ("NAC_KP_XY", math.nan, "NAC_KP_XY=nan is not a number"),
])
def test_what_arducopter_refuses_is_refused_with_the_reason(name, value, reason):
    table = ParamTable(1)
    with pytest.raises(ParamError, match=reason.replace("(", r"\(").replace(")", r"\)")):
        table.store(0, name, value)


def test_files_and_scenarios_are_strict_an_out_of_range_value_is_an_error():
    table = ParamTable(1)
    with pytest.raises(ParamError, match=r"WPNAV_SPEED=3000 outside 20..2000"):
        table.set(0, "WPNAV_SPEED", 3000.0)
    assert table.get(0, "WPNAV_SPEED") == 500.0
