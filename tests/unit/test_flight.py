"""Flight logic driven through the pure physics: mission items, modes and failsafes without sockets."""

import numpy as np
import pytest

from missions.geo import Home, enu_to_lla
from missions.model import Frame, MavCmd, MissionItem
from sitl.vehicle.flight import Autopilots, Check, CopterMode, Event, MissionState, Result
from sitl.vehicle.params import ParamTable
from sitl.vehicle.physics import VehicleState, step

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced

HOME = Home(47.397742, 8.545594, 488.0)


def make(n=1):
    params = ParamTable(n)
    fleet = Autopilots([HOME] * n, params)
    state = VehicleState.at_rest(n, params.physics())
    fleet.update(state, 0.0)
    return fleet, state, params


def run(fleet, state, params, seconds, t0=0.0, dt=0.02, until=None):
    physics = params.physics()
    t = t0
    for _ in range(int(seconds / dt)):
        state = step(state, fleet.command(), physics, dt)
        t += dt
        fleet.update(state, t)
        if until is not None and until(fleet, state):
            break
    return state, t


def wp(seq, east, north, alt=10.0, cmd=MavCmd.NAV_WAYPOINT, **kw):
    lat, lon, _ = enu_to_lla(np.array([east, north, 0.0]), HOME)
    return MissionItem(seq, cmd, Frame.GLOBAL_RELATIVE_ALT_INT, lat_deg=float(lat), lon_deg=float(lon), alt_m=alt,
                       **kw)


def reached(fleet):
    return [v for _, kind, v in fleet.events if kind == Event.ITEM_REACHED]


def test_loiter_time_holds_for_its_seconds_and_jump_repeats():
    fleet, state, params = make()
    mission = [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=5),
               wp(2, 10, 0, 5, MavCmd.NAV_LOITER_TIME, p1=4.0), wp(3, 0, 10, 5),
               MissionItem(4, MavCmd.DO_JUMP, p1=2, p2=1), MissionItem(5, MavCmd.NAV_LAND)]
    fleet.replace_mission(0, 0, mission)
    assert fleet.arm(0, True).result == Result.ACCEPTED
    assert fleet.mission_start(0, 0).result == Result.ACCEPTED
    hold = {}

    def watch(f, s):
        if f.current_seq[0] == 2 and f.check[0] == Check.TIMER:
            hold.setdefault("start", f.t_s)
        if f.current_seq[0] == 3:
            hold.setdefault("end", f.t_s)
        return f.mission_state[0] == MissionState.COMPLETE

    state, t = run(fleet, state, params, 400, until=watch)
    assert abs(hold["end"] - hold["start"] - 4.0) <= 0.05
    assert reached(fleet) == [1, 2, 3, 2, 3, 5]  # jumped back once; DO_JUMP itself is not "reached"
    assert state.on_ground[0]
    assert fleet.mission_state[0] == MissionState.COMPLETE


def test_change_speed_limits_the_horizontal_speed():
    fleet, state, params = make()
    mission = [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=5),
               MissionItem(2, MavCmd.DO_CHANGE_SPEED, p1=1, p2=1.5), wp(3, 200, 0, 5)]
    fleet.replace_mission(0, 0, mission)
    fleet.arm(0, True)
    fleet.mission_start(0, 0)
    state, _ = run(fleet, state, params, 40)
    assert abs(np.hypot(*state.vel_mps[0, :2]) - 1.5) < 0.01


def test_rtl_climbs_returns_and_lands_then_disarms():
    fleet, state, params = make()
    fleet.arm(0, True)
    fleet.takeoff(0, 5.0)
    state, t = run(fleet, state, params, 10)
    fleet.mode[0] = CopterMode.GUIDED
    fleet.goto(0, [30.0, 20.0, 5.0])
    state, t = run(fleet, state, params, 60, t)
    fleet.set_mode(0, CopterMode.RTL)
    peak = [0.0]

    def watch(f, s):
        peak[0] = max(peak[0], s.pos_m[0, 2])
        return not f.armed[0]

    state, t = run(fleet, state, params, 200, t, until=watch)
    assert peak[0] >= 15.0 - 0.5  # RTL_ALT 1500 cm
    assert not fleet.armed[0] and state.on_ground[0]
    assert np.hypot(*state.pos_m[0, :2]) < 2.0


def test_disarm_in_flight_needs_force_and_modes_validate():
    fleet, state, params = make()
    fleet.arm(0, True)
    fleet.takeoff(0, 5.0)
    state, _ = run(fleet, state, params, 10)
    assert fleet.arm(0, False).result == Result.DENIED
    assert fleet.set_mode(0, 1234).result == Result.DENIED
    assert fleet.arm(0, False, force=True).result == Result.ACCEPTED


def test_low_battery_failsafe_lands_when_configured():
    fleet, state, params = make()
    params.set(0, "BATT_FS_LOW_ACT", 1)
    fleet.arm(0, True)
    fleet.takeoff(0, 5.0)
    state, t = run(fleet, state, params, 10)
    state = VehicleState(**{**state.__dict__, "soc": np.array([0.1])})
    fleet.update(state, t)
    assert fleet.mode[0] == CopterMode.LAND and fleet.failsafe[0]
