import numpy as np
import pytest

from sitl.vehicle import energy
from sitl.vehicle.physics import (
    Command,
    Motion,
    PhysicsParams,
    VehicleState,
    attitude_rad,
    desired_velocity_mps,
    drain,
    gps_noise_m,
    step,
)

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced


def command(n, motion, goal, armed=True, speed=5.0):
    return Command(motion=np.full(n, motion), goal_m=np.tile(np.asarray(goal, float), (n, 1)),
                   armed=np.full(n, armed), speed_xy_mps=np.full(n, speed))


def fly(state, cmd, params, seconds, dt=0.01):
    for _ in range(int(round(seconds / dt))):
        state = step(state, cmd, params, dt)
    return state


def test_controller_is_proportional_and_points_toward_the_goal():
    p = PhysicsParams.defaults(1)
    v = desired_velocity_mps(np.array([[0.0, 0.0, 5.0]]), np.array([[4.0, -2.0, 6.0]]), p, np.array([5.0]))
    # k_x = k_y = 0.15, k_z = 1: the converging sign, v = k (goal - position)
    assert v[0] == pytest.approx([0.6, -0.3, 1.0])


def test_horizontal_clamp_keeps_direction_and_vertical_clamps_are_separate():
    p = PhysicsParams.defaults(1)
    v = desired_velocity_mps(np.array([[0.0, 0.0, 50.0]]), np.array([[300.0, 400.0, 0.0]]), p, np.array([5.0]))
    assert np.hypot(v[0, 0], v[0, 1]) == pytest.approx(5.0)
    assert v[0, 0] / v[0, 1] == pytest.approx(0.75)
    assert v[0, 2] == pytest.approx(-1.5)
    v = desired_velocity_mps(np.array([[0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, 100.0]]), p, np.array([2.0]))
    assert v[0, 2] == pytest.approx(2.5)
    # a mission speed below the parameter limit wins
    v = desired_velocity_mps(np.array([[0.0, 0.0, 0.0]]), np.array([[100.0, 0.0, 0.0]]), p, np.array([2.0]))
    assert v[0, 0] == pytest.approx(2.0)


def test_gains_are_per_vehicle():
    p = PhysicsParams.defaults(2)
    p.k_xy[1] = 0.3
    v = desired_velocity_mps(np.zeros((2, 3)), np.array([[10.0, 0, 0], [10.0, 0, 0]]), p, np.full(2, 5.0))
    assert v[:, 0] == pytest.approx([1.5, 3.0])


def test_velocity_follows_first_order_response():
    p = PhysicsParams.defaults(1)
    s = VehicleState.at_rest(1, p)
    s = fly(s, command(1, Motion.GOTO, [0, 0, 10]), p, 0.3)  # one time constant
    # desired vertical speed is clamped at 2.5 m/s; after tau the response reaches ~63 %
    assert s.vel_mps[0, 2] == pytest.approx(2.5 * (1 - np.exp(-1)), rel=0.05)


def test_converges_to_waypoint_and_holds():
    p = PhysicsParams.defaults(3)
    s = VehicleState.at_rest(3, p)
    goal = np.array([[30.0, -20.0, 10.0], [0.0, 5.0, 3.04], [-50.0, 0.0, 20.0]])
    cmd = Command(np.full(3, Motion.GOTO), goal, np.ones(3, bool), np.full(3, 5.0))
    s = fly(s, cmd, p, 60.0)
    assert np.linalg.norm(s.pos_m - goal, axis=1).max() < 0.05
    assert np.abs(s.vel_mps).max() < 0.05
    assert not s.on_ground.any()


def test_lands_and_stays_down():
    p = PhysicsParams.defaults(1)
    s = VehicleState.at_rest(1, p)
    s = fly(s, command(1, Motion.GOTO, [5, 5, 10]), p, 20.0)
    s = fly(s, command(1, Motion.LAND, [5, 5, 0]), p, 10.0)
    assert s.pos_m[0, 2] > 3.0 and not s.on_ground[0]  # 0.5 m/s: still descending after 10 s
    s = fly(s, command(1, Motion.LAND, [5, 5, 0]), p, 15.0)
    assert s.on_ground[0] and s.pos_m[0, 2] == 0.0
    assert s.pos_m[0, :2] == pytest.approx([5, 5], abs=0.05)
    s = fly(s, command(1, Motion.IDLE, [5, 5, 0], armed=False), p, 2.0)
    assert s.on_ground[0] and np.abs(s.vel_mps).max() == 0.0


def test_disarmed_vehicle_does_not_move():
    p = PhysicsParams.defaults(1)
    s = fly(VehicleState.at_rest(1, p), command(1, Motion.GOTO, [10, 10, 10], armed=False), p, 5.0)
    assert np.abs(s.pos_m).max() == 0.0 and s.on_ground[0]


def test_the_pack_delivers_the_frames_power_while_flying_and_the_avionics_on_the_ground():
    """Climbing 10 m and hovering for 120 s draws Zeng's hover power through the drive, plus W h for the climb and
    the avionics, within 1 % (the first-order velocity response and the settling at 10 m are the rest); the
    vehicle on the ground draws only its avionics; charge and state of charge agree; flying sags the voltage."""
    p = PhysicsParams.defaults(2)
    s = VehicleState.at_rest(2, p)
    cmd = Command(np.array([Motion.GOTO, Motion.IDLE]), np.array([[0, 0, 10.0], [0, 0, 0]]),
                  np.array([True, False]), np.full(2, 5.0))
    for _ in range(1200):  # the kinematics at 50 Hz, the packs at 10 Hz as the world steps them
        for _ in range(5):
            s = step(s, cmd, p, 0.02)
        s = drain(s, p, cmd.armed, 0.1)
    frame = energy.FRAMES["zeng-2019"]
    hover_w = float(energy.level_power_w(frame, 0.0)) / frame.drive_efficiency + frame.avionics_w
    expected_wh = (hover_w * 120.0 + frame.weight_n * 10.0 / frame.drive_efficiency) / 3600.0
    assert s.consumed_wh[0] == pytest.approx(expected_wh, rel=0.01)
    assert s.consumed_wh[1] == pytest.approx(frame.avionics_w * 120.0 / 3600.0, rel=1e-3)
    assert s.consumed_mah[0] == pytest.approx((1 - s.soc[0]) * 5000, rel=1e-6)
    assert s.voltage_v[0] < s.voltage_v[1] < 16.8


def test_attitude_tilts_into_acceleration():
    p = PhysicsParams.defaults(1)
    s = VehicleState.at_rest(1, p)
    s = fly(s, command(1, Motion.GOTO, [0, 0, 10]), p, 10.0)
    s = fly(s, command(1, Motion.GOTO, [0, 100, 10]), p, 0.1)
    roll, pitch, yaw = attitude_rad(s)
    assert pitch[0] < -0.05 and abs(roll[0]) < 1e-3 and yaw[0] == pytest.approx(0.0, abs=1e-6)


def test_gps_noise_is_deterministic_for_a_seed():
    a = gps_noise_m(np.random.default_rng(7), 4, 1.0, 2.0)
    b = gps_noise_m(np.random.default_rng(7), 4, 1.0, 2.0)
    assert np.array_equal(a, b) and a.std() > 0.1
    assert not gps_noise_m(np.random.default_rng(7), 4, 0.0, 0.0).any()


def test_step_is_deterministic():
    p = PhysicsParams.defaults(2)
    cmd = command(2, Motion.GOTO, [3, 4, 5])
    a = fly(VehicleState.at_rest(2, p), cmd, p, 3.0)
    b = fly(VehicleState.at_rest(2, p), cmd, p, 3.0)
    assert np.array_equal(a.pos_m, b.pos_m)
