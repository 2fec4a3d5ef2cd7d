"""GUIDED setpoints as ArduCopter reads them: every frame and type-mask combination of SET_POSITION_TARGET_*
against the motion it must produce, through the pure flight logic and physics (no sockets)."""

import math

import numpy as np
import pytest

from sitl.vehicle import guided
from sitl.vehicle.flight import Autopilots, CopterMode, Phase
from sitl.vehicle.guided import ACC_IGNORE, POS_IGNORE, VEL_IGNORE, YAW_IGNORE, YAW_RATE_IGNORE
from tests.unit.test_flight import HOME, make, run

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced

ONLY_POS = VEL_IGNORE | ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE
ONLY_VEL = POS_IGNORE | ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE
ONLY_ACC = POS_IGNORE | VEL_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE
NOTHING = POS_IGNORE | VEL_IGNORE | ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE


def airborne(heading_deg: float = 0.0):
    """One copter hovering at 10 m over home in GUIDED, facing `heading_deg`."""
    fleet, state, params = make()
    fleet.set_mode(0, CopterMode.GUIDED)
    fleet.arm(0, True)
    fleet.takeoff(0, 10.0)
    state, t = run(fleet, state, params, 30.0, until=lambda f, s: f.phase[0] == Phase.NONE and s.pos_m[0, 2] > 9.8)
    if heading_deg:
        fleet.setpoint(0, guided.Setpoint(yaw_rad=math.radians(heading_deg)))
        state, t = run(fleet, state, params, 5.0, t0=t)
    return fleet, state, params, t


def local(frame, mask, xyz=(0, 0, 0), vel=(0, 0, 0), acc=(0, 0, 0), yaw=0.0, yaw_rate=0.0, state=None):
    return guided.local_setpoint(frame, mask, xyz, vel, acc, yaw, yaw_rate, state.pos_m[0].copy(),
                                 float(state.yaw_rad[0]))


@pytest.mark.parametrize("frame, xyz, expected_enu", [
    (guided.LOCAL_NED, (20.0, 10.0, -15.0), (10.0, 20.0, 15.0)),  # about home
    (guided.LOCAL_OFFSET_NED, (20.0, 10.0, -5.0), (10.0, 20.0, 15.0)),  # about the vehicle (at 0, 0, 10)
    (guided.BODY_OFFSET_NED, (20.0, 10.0, -5.0), (-20.0, 10.0, 15.0)),  # facing west: forward is -east
    (guided.BODY_NED, (20.0, 10.0, 0.0), (-20.0, 10.0, 10.0)),
])
def test_a_position_setpoint_flies_to_the_point_its_frame_means(frame, xyz, expected_enu):
    fleet, state, params, t = airborne(heading_deg=-90.0)
    start = state.pos_m[0].copy()
    target = local(frame, ONLY_POS, xyz=xyz, state=state)
    assert fleet.setpoint(0, target)
    state, _ = run(fleet, state, params, 60.0, t0=t)
    expected = np.array(expected_enu) + (start * [1, 1, 0] if frame != guided.LOCAL_NED else 0)
    assert state.pos_m[0] == pytest.approx(expected, abs=0.3)


@pytest.mark.parametrize("frame, vel_ned, heading_deg, expected_dir_enu", [
    (guided.LOCAL_NED, (2.0, 0.0, 0.0), 0.0, (0.0, 1.0)),  # north
    (guided.LOCAL_OFFSET_NED, (0.0, 2.0, 0.0), 0.0, (1.0, 0.0)),  # east
    (guided.BODY_NED, (2.0, 0.0, 0.0), 90.0, (1.0, 0.0)),  # forward while facing east
    (guided.BODY_OFFSET_NED, (0.0, 2.0, 0.0), 90.0, (0.0, -1.0)),  # right while facing east: south
])
def test_a_velocity_only_setpoint_flies_that_way_at_that_speed_and_keeps_its_height(
        frame, vel_ned, heading_deg, expected_dir_enu):
    fleet, state, params, t = airborne(heading_deg)
    start = state.pos_m[0].copy()
    assert fleet.setpoint(0, local(frame, ONLY_VEL, vel=vel_ned, state=state))
    state, t = run(fleet, state, params, 2.5, t0=t)  # inside the 3 s timeout
    moved = state.pos_m[0] - start
    assert moved[:2] / np.linalg.norm(moved[:2]) == pytest.approx(expected_dir_enu, abs=0.02)
    assert np.hypot(*state.vel_mps[0, :2]) == pytest.approx(2.0, abs=0.1)
    assert state.pos_m[0, 2] == pytest.approx(10.0, abs=0.2), "no descent toward z = 0"


def test_velocity_control_stops_three_seconds_after_the_last_setpoint():
    fleet, state, params, t = airborne()
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_VEL, vel=(3.0, 0.0, 0.0), state=state))
    for _ in range(3):  # renewed every 2 s: keeps going
        state, t = run(fleet, state, params, 2.0, t0=t)
        assert np.hypot(*state.vel_mps[0, :2]) > 2.5
        fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_VEL, vel=(3.0, 0.0, 0.0), state=state))
    state, t = run(fleet, state, params, 2.9, t0=t)
    assert np.hypot(*state.vel_mps[0, :2]) > 2.5
    state, t = run(fleet, state, params, 3.0, t0=t)
    assert np.hypot(*state.vel_mps[0, :2]) < 0.2, "stopped after the timeout"
    assert any("no velocity setpoint for 3 s" in str(v) for _, _, v in fleet.events)


def test_acceleration_only_is_followed_from_the_current_velocity():
    fleet, state, params, t = airborne()
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_ACC, acc=(0.0, 1.0, 0.0), state=state))
    state, t = run(fleet, state, params, 2.0, t0=t)
    assert state.vel_mps[0, 0] == pytest.approx(2.0, abs=0.4) and abs(state.vel_mps[0, 1]) < 0.1


def test_climb_and_descent_by_velocity_obey_the_limits():
    fleet, state, params, t = airborne()
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_VEL, vel=(0.0, 0.0, -10.0), state=state))  # up, 10 m/s asked
    state, t = run(fleet, state, params, 2.0, t0=t)
    assert state.vel_mps[0, 2] == pytest.approx(params.get(0, "WPNAV_SPEED_UP") / 100, abs=0.05)


def test_position_and_velocity_together_go_to_the_position_and_all_ignored_stops():
    fleet, state, params, t = airborne()
    both = local(guided.LOCAL_NED, ACC_IGNORE | YAW_IGNORE | YAW_RATE_IGNORE,
                 xyz=(0.0, 15.0, -10.0), vel=(0.0, 1.0, 0.0), state=state)
    fleet.setpoint(0, both)
    state, t = run(fleet, state, params, 2.0, t0=t)
    assert state.vel_mps[0, 0] > 0.5
    fleet.setpoint(0, local(guided.LOCAL_NED, NOTHING, state=state))
    state, t = run(fleet, state, params, 8.0, t0=t)
    assert np.linalg.norm(state.vel_mps[0]) < 0.1 and state.pos_m[0, 0] < 14.0, "stopped short of the target"


@pytest.mark.parametrize("mask_extra, yaw, yaw_rate, expected_deg", [
    (YAW_RATE_IGNORE, math.radians(135.0), 0.0, 135.0),
    (YAW_IGNORE, 0.0, math.radians(-20.0), -60.0),  # 3 s at -20 deg/s
])
def test_yaw_and_yaw_rate_turn_the_vehicle(mask_extra, yaw, yaw_rate, expected_deg):
    fleet, state, params, t = airborne()
    mask = POS_IGNORE | VEL_IGNORE | ACC_IGNORE | mask_extra
    fleet.setpoint(0, local(guided.LOCAL_NED, mask, yaw=yaw, yaw_rate=yaw_rate, state=state))
    state, t = run(fleet, state, params, 3.0, t0=t)
    assert math.degrees(state.yaw_rad[0]) == pytest.approx(expected_deg, abs=2.0)


@pytest.mark.parametrize("frame, alt, relative_expected", [(6, 25.0, 25.0), (11, 25.0, 25.0), (5, 513.0, 25.0)])
def test_global_frames_take_altitude_above_home_or_sea_level(frame, alt, relative_expected):
    from sitl.vehicle.world import World

    world = World([HOME])
    pos = world.global_to_enu(0, HOME.lat_deg + 0.0002, HOME.lon_deg, alt,
                              relative=frame in guided.GLOBAL_RELATIVE_FRAMES)
    target = guided.global_setpoint(frame, ONLY_POS, pos, (0, 0, 0), (0, 0, 0), 0.0, 0.0)
    assert target.pos_m[2] == pytest.approx(relative_expected) and target.pos_m[1] == pytest.approx(22.2, abs=0.2)
    velocity = guided.global_setpoint(frame, ONLY_VEL, None, (1.0, -2.0, 0.5), (0, 0, 0), 0.0, 0.0)
    assert velocity.is_velocity_control and list(velocity.vel_mps) == [-2.0, 1.0, -0.5]


def test_setpoints_are_ignored_outside_guided_on_the_ground_in_other_frames_and_when_not_finite():
    fleet, state, params = make()
    fleet.set_mode(0, CopterMode.GUIDED)
    fleet.arm(0, True)
    assert not fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_VEL, vel=(1, 0, 0), state=state)), "on the ground"
    fleet, state, params, t = airborne()
    fleet.set_mode(0, CopterMode.LOITER)
    assert not fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_VEL, vel=(1, 0, 0), state=state))
    assert local(12, ONLY_POS, state=state) is None  # MAV_FRAME_LOCAL_ENU: not taken by ArduCopter
    assert local(guided.LOCAL_NED, ONLY_POS, xyz=(math.nan, 0, 0), state=state) is None
    assert guided.global_setpoint(1, ONLY_POS, np.zeros(3), (0, 0, 0), (0, 0, 0), 0, 0) is None


def test_fleet_command_carries_the_setpoint_arrays():
    fleet = Autopilots([HOME], make()[2])
    cmd = fleet.command()
    assert cmd.velocity_mps.shape == (1, 3) and np.isnan(cmd.yaw_target_rad).all()


def test_condition_yaw_turns_absolute_or_relative_at_the_asked_rate():
    fleet, state, params, t = airborne()
    assert fleet.condition_yaw(0, 90.0, 30.0, 1, relative=False).result == 0
    state, t = run(fleet, state, params, 1.5, t0=t)
    assert math.degrees(state.yaw_rad[0]) == pytest.approx(45.0, abs=2.0), "30 deg/s for 1.5 s"
    state, t = run(fleet, state, params, 3.0, t0=t)
    assert math.degrees(state.yaw_rad[0]) == pytest.approx(90.0, abs=1.0)
    fleet.condition_yaw(0, 40.0, 0.0, -1, relative=True)
    state, t = run(fleet, state, params, 2.0, t0=t)
    assert math.degrees(state.yaw_rad[0]) == pytest.approx(50.0, abs=1.0)
    assert fleet.condition_yaw(0, 400.0, 0.0, 1, relative=False).result != 0


def test_a_region_of_interest_keeps_the_nose_on_it_while_flying_past():
    fleet, state, params, t = airborne()
    fleet.set_roi(0, np.array([0.0, 50.0, 0.0]))  # 50 m north
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_VEL, vel=(0.0, 3.0, 0.0), state=state))  # east
    state, t = run(fleet, state, params, 2.5, t0=t)
    bearing = math.degrees(math.atan2(0.0 - state.pos_m[0, 0], 50.0 - state.pos_m[0, 1]))
    assert math.degrees(state.yaw_rad[0]) == pytest.approx(bearing, abs=3.0) and bearing < -5.0
    fleet.set_roi(0, None)
    assert math.isnan(fleet.roi_m[0, 0])


def test_pause_stops_a_mission_where_it_is_and_continue_flies_on():
    from missions.model import MavCmd, MissionItem
    from sitl.vehicle.flight import MissionState
    from tests.unit.test_flight import wp

    fleet, state, params = make()
    fleet.replace_mission(0, 0, [MissionItem(0, 16), MissionItem(1, MavCmd.NAV_TAKEOFF, alt_m=5),
                                 wp(2, 0, 60, 5), MissionItem(3, MavCmd.NAV_LAND)])
    fleet.arm(0, True)
    fleet.mission_start(0, 0)
    state, t = run(fleet, state, params, 60.0, until=lambda f, s: s.pos_m[0, 1] > 20.0)
    paused_at = state.pos_m[0, 1]
    assert fleet.pause(0, True).result == 0 and fleet.mission_state[0] == MissionState.PAUSED
    state, t = run(fleet, state, params, 20.0, t0=t)
    assert np.linalg.norm(state.vel_mps[0]) < 0.1 and abs(state.pos_m[0, 1] - paused_at) < 2.0
    assert int(fleet.current_seq[0]) == 2
    assert fleet.pause(0, False).result == 0 and fleet.mission_state[0] == MissionState.ACTIVE
    state, t = run(fleet, state, params, 120.0, t0=t, until=lambda f, s: f.mission_state[0] == MissionState.COMPLETE)
    assert fleet.mission_state[0] == MissionState.COMPLETE and state.pos_m[0, 1] == pytest.approx(60.0, abs=2.5)
    fleet.set_mode(0, CopterMode.LOITER)
    assert fleet.pause(0, True).result != 0, "only in AUTO or GUIDED"


def test_servos_are_remembered_except_the_motors_and_reboot_needs_a_disarmed_vehicle():
    fleet, state, params, t = airborne()
    assert fleet.set_servo(0, 9, 1900).result == 0 and fleet.servo_pwm[0] == {9: 1900}
    assert fleet.set_servo(0, 2, 1500).result != 0
    assert fleet.reboot(0).result != 0 and fleet.armed[0], "armed: refused"
    fleet, state, params = make()
    fleet.set_mode(0, CopterMode.GUIDED)
    assert fleet.reboot(0).result == 0 and fleet.mode[0] == CopterMode.STABILIZE


def test_a_copter_armed_on_the_ground_disarms_itself_after_disarm_delay_unless_it_takes_off():
    fleet, state, params = make()
    fleet.arm(0, True)
    state, t = run(fleet, state, params, 9.5)
    assert fleet.armed[0]
    state, t = run(fleet, state, params, 1.0, t0=t)
    assert not fleet.armed[0] and any("Auto-disarmed" in str(v) for _, _, v in fleet.events)
    fleet.arm(0, True)  # again: a fresh 10 s, and a takeoff within them keeps it armed
    state, t = run(fleet, state, params, 5.0, t0=t)
    fleet.set_mode(0, CopterMode.GUIDED)
    fleet.takeoff(0, 5.0)
    state, t = run(fleet, state, params, 20.0, t0=t)
    assert fleet.armed[0] and state.pos_m[0, 2] > 4.0
    fleet2, state2, params2 = make()
    params2.set(0, "DISARM_DELAY", 0)
    fleet2.arm(0, True)
    state2, _ = run(fleet2, state2, params2, 30.0)
    assert fleet2.armed[0], "0: never"


def test_rc_override_flies_a_pilot_mode_by_the_sticks_and_times_out_into_a_hold():
    from sitl.vehicle import pilot

    fleet, state, params, t = airborne()
    fleet.set_mode(0, CopterMode.LOITER)
    sticks = [1500, 1300, 1500, 1500] + [pilot.IGNORE] * 12  # pitch forward: fly north
    fleet.rc_override(0, sticks)
    for _ in range(4):  # renewed every 2 s, as a joystick app sends
        state, t = run(fleet, state, params, 2.0, t0=t)
        fleet.rc_override(0, sticks)
    assert state.vel_mps[0, 1] > 3.0 and abs(state.vel_mps[0, 0]) < 0.2 and fleet.piloted[0]
    fleet.rc_override(0, [1500, 1500, 1900, 1700] + [pilot.IGNORE] * 12)  # climb and turn clockwise
    state, t = run(fleet, state, params, 2.0, t0=t)
    assert state.vel_mps[0, 2] > 1.0 and 30.0 < math.degrees(state.yaw_rad[0]) < 90.0
    state, t = run(fleet, state, params, 4.0, t0=t)  # no renewal: released after 3 s, holds
    assert not fleet.rc_overridden[0].any() and not fleet.piloted[0]
    assert np.linalg.norm(state.vel_mps[0]) < 0.5
    assert any("RC override timed out" in str(v) for _, _, v in fleet.events)
    fleet.set_mode(0, CopterMode.GUIDED)
    fleet.rc_override(0, sticks)
    state, t = run(fleet, state, params, 2.0, t0=t)
    assert not fleet.piloted[0], "GUIDED is not flown by the sticks"


def test_stick_mapping_dead_zones_and_release():
    from sitl.vehicle import pilot

    channels, overridden = pilot.idle_channels(), np.zeros(pilot.CHANNELS, dtype=bool)
    pilot.apply_override(channels, overridden, [1510, 2000, 1540, 0] + [pilot.IGNORE] * 12)
    assert list(channels[:4]) == [1510, 2000, 1540, 1500] and list(overridden[:4]) == [True, True, True, False]
    velocity, yaw_rate = pilot.stick_command(channels, True, 0.0, 10.0, 2.5, 1.5)
    assert velocity[0] == 0.0 and velocity[1] == pytest.approx(-10.0) and velocity[2] == 0.0 and yaw_rate == 0.0
    velocity, _ = pilot.stick_command(pilot.idle_channels(), False, 0.0, 10.0, 2.5, 1.5)
    assert not velocity.any(), "no pilot: hold"
