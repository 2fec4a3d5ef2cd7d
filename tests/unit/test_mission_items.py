"""Mission items a copter flies as ArduCopter does (loiter turns, delays, unlimited loiter, splines, yaw and ROI,
servos and camera items acknowledged), through the pure flight logic; and what an upload refuses."""

import math

import numpy as np
import pytest

from missions import firmware
from missions.model import Frame, MavCmd, MissionItem, MissionType
from sitl.vehicle import mission_items as items_
from sitl.vehicle.flight import Event, MissionState, Phase
from tests.unit.test_flight import make, run, wp

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced


def fly(mission, seconds, until=None):
    fleet, state, params = make()
    fleet.replace_mission(0, 0, mission)
    fleet.arm(0, True)
    fleet.mission_start(0, 0)
    trace = []

    def watch(f, s):
        trace.append((f.t_s, s.pos_m[0].copy(), float(s.yaw_rad[0]), int(f.current_seq[0])))
        return until(f, s) if until else f.mission_state[0] == MissionState.COMPLETE

    state, t = run(fleet, state, params, seconds, until=watch)
    return fleet, state, trace


def test_loiter_turns_go_round_the_circle_the_asked_number_of_times_at_circle_rate():
    centre = wp(2, 0, 30, 8, MavCmd.NAV_LOITER_TURNS, p1=2.0, p3=10.0)
    mission = [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=8), centre, wp(3, 0, 0, 8)]
    fleet, state, trace = fly(mission, 200.0)
    assert fleet.mission_state[0] == MissionState.COMPLETE
    on_circle = [(t, p) for t, p, _, seq in trace if seq == 2 and fleet is not None]
    circling = [(t, p) for t, p in on_circle if abs(np.hypot(p[0], p[1] - 30.0) - 10.0) < 1.5]
    assert len(circling) > 100, "flew on the 10 m circle"
    duration_s = circling[-1][0] - circling[0][0]
    assert duration_s == pytest.approx(2 * 360 / items_.CIRCLE_RATE_DPS, rel=0.15), "2 turns at 20 deg/s"
    bearings = [math.atan2(p[0], p[1] - 30.0) for _, p in circling[:50]]
    assert np.mean(np.diff(np.unwrap(bearings))) > 0, "positive radius: clockwise"


def test_a_nav_delay_waits_in_place_and_loiter_unlimited_stays_until_told():
    mission = [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=5),
               MissionItem(2, firmware.NAV_DELAY, frame=Frame.MISSION, p1=6.0), wp(3, 20, 0, 5),
               wp(4, 0, 20, 5, MavCmd.NAV_LOITER_UNLIM)]
    fleet, state, trace = fly(mission, 120.0, until=lambda f, s: f.t_s > 100)
    at_delay = [t for t, _, _, seq in trace if seq == 2]
    assert at_delay[-1] - at_delay[0] == pytest.approx(6.0, abs=0.1)
    assert int(fleet.current_seq[0]) == 4 and fleet.phase[0] == Phase.LOITER_UNLIM
    assert fleet.mission_state[0] == MissionState.ACTIVE and np.hypot(*(state.pos_m[0, :2] - [0, 20])) < 0.5


def test_do_items_point_the_nose_set_servos_and_camera_items_pass_over():
    mission = [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=5),
               MissionItem(2, MavCmd.CONDITION_YAW, frame=Frame.MISSION, p1=180.0, p2=0, p3=1, p4=0),
               MissionItem(3, 203, frame=Frame.MISSION),  # DO_DIGICAM_CONTROL: no camera, no effect
               MissionItem(4, firmware.DO_SET_SERVO, frame=Frame.MISSION, p1=9, p2=1700),
               wp(5, 0, 0, 5, MavCmd.NAV_LOITER_TIME, p1=5.0),
               wp(6, 30, 0, 5, firmware.DO_SET_ROI),  # look east while flying north
               wp(7, 0, 40, 5, firmware.NAV_SPLINE_WAYPOINT)]
    fleet, state, trace = fly(mission, 120.0)
    assert fleet.mission_state[0] == MissionState.COMPLETE and fleet.servo_pwm[0] == {9: 1700}
    loiter_yaws = [yaw for _, _, yaw, seq in trace if seq == 5]
    assert abs(abs(math.degrees(loiter_yaws[-1])) - 180.0) < 2.0
    flying_north = [(p, yaw) for _, p, yaw, seq in trace if seq == 7 and 10 < p[1] < 30]
    for p, yaw in flying_north[::20]:
        assert math.degrees(yaw) == pytest.approx(math.degrees(math.atan2(30 - p[0], 0 - p[1])), abs=5.0)
    reached = [v for _, kind, v in fleet.events if kind == Event.ITEM_REACHED]
    assert reached[:6] == [1, 2, 3, 4, 5, 6] and np.hypot(*(state.pos_m[0, :2] - [0, 40])) < 2.5


@pytest.mark.parametrize("command, accepted", [
    (firmware.NAV_SPLINE_WAYPOINT, True), (MavCmd.NAV_LOITER_TURNS, True), (firmware.NAV_DELAY, True),
    (MavCmd.NAV_LOITER_UNLIM, True), (firmware.DO_SET_ROI, True), (MavCmd.CONDITION_YAW, True),
    (firmware.DO_SET_SERVO, True), (208, True), (2000, True), (firmware.NAV_VTOL_TAKEOFF, True),
    (42702, False),  # NAV_SCRIPT_TIME: needs Lua scripting
    (31, False),  # NAV_LOITER_TO_ALT: a plane's
    (9999, False),
])
def test_an_upload_refuses_only_what_the_copter_does_not_take(command, accepted):
    item = MissionItem(1, command, Frame.GLOBAL_RELATIVE_ALT_INT, lat_deg=47.4, lon_deg=8.5, alt_m=10)
    assert (firmware.arducopter_refusal(item, 0) is None) == accepted


@pytest.mark.parametrize("vertex_count, refusal", [(0, "MAV_MISSION_INVALID_PARAM1"), (2, "MAV_MISSION_INVALID_PARAM1"),
                                                   (3.5, "MAV_MISSION_INVALID_PARAM1"), (3, None), (12, None)])
def test_a_fence_polygon_vertex_needs_a_vertex_count_of_three_or_more(vertex_count, refusal):
    """NAC's validator refused a file holding such a polygon while the SITL took it over MAVLink (issue 33)."""
    vertex = MissionItem(0, MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION, Frame.GLOBAL_INT, p1=vertex_count,
                         lat_deg=47.4, lon_deg=8.5, mission_type=MissionType.FENCE)
    assert firmware.arducopter_refusal(vertex, MissionType.FENCE) == refusal


@pytest.mark.parametrize("law, leg_s", [(0, (9.5, 13.0)), (1, (20.0, 23.0))])
def test_a_50_m_leg_takes_arducopters_trapezoid_time_or_the_research_laws(law, leg_s):
    """ArduCopter's WPNav: accelerate at 2.5 m/s^2 to 5 m/s, cruise, brake: about 12 s for 50 m. The research's
    proportional law approaches asymptotically: 21 s to within the 2 m acceptance radius."""
    fleet, state, params = make()
    params.set(0, "NAC_NAV_LAW", law)
    fleet.replace_mission(0, 0, [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=10),
                                 wp(2, 0, 50, 10), wp(3, 0, 60, 10)])
    fleet.arm(0, True)
    fleet.mission_start(0, 0)
    times = {}

    def watch(f, s):
        times.setdefault(int(f.current_seq[0]), f.t_s)
        return int(f.current_seq[0]) == 3

    run(fleet, state, params, 120.0, until=watch)
    assert leg_s[0] < times[3] - times[2] < leg_s[1]


def test_land_comes_down_fast_then_at_land_speed_and_do_change_speed_may_exceed_wpnav_speed():
    fleet, state, params = make()
    fleet.replace_mission(0, 0, [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=30),
                                 MissionItem(2, MavCmd.DO_CHANGE_SPEED, Frame.MISSION, p2=8.0), wp(3, 0, 100, 30),
                                 MissionItem(4, MavCmd.NAV_LAND)])
    fleet.arm(0, True)
    fleet.mission_start(0, 0)
    samples = []
    run(fleet, state, params, 200.0, until=lambda f, s: samples.append((int(f.current_seq[0]), s.vel_mps[0].copy(),
                                                                          s.pos_m[0, 2])) or not f.armed[0])
    cruise = max(np.hypot(*v[:2]) for seq, v, _ in samples if seq == 3)
    assert cruise == pytest.approx(8.0, abs=0.1), "8 m/s asked, above WPNAV_SPEED's 5"
    high = [-v[2] for seq, v, z in samples if seq == 4 and 15.0 < z < 25.0]
    low = [-v[2] for seq, v, z in samples if seq == 4 and 1.0 < z < 5.0]
    assert max(high) == pytest.approx(1.5, abs=0.05) and max(low) == pytest.approx(0.5, abs=0.05)
