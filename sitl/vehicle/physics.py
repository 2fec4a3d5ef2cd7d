"""Quadrotor point-mass physics, vectorised over vehicles (pure: no sockets, files or clocks).

`step(state, cmd, params, dt_s) -> state` advances every vehicle at once with array operations; the flight
logic above it decides goals and motions, the MAVLink layer only reads the result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import IntEnum
from functools import cached_property

import numpy as np

from sitl.vehicle import energy
from sitl.vehicle.energy import GRAVITY_MPS2

BATTERY_PERIOD_S = 0.1  # how often the packs are stepped: ArduPilot's battery monitor reads at 10 Hz
YAW_RATE_MAX_RPS = math.radians(90.0)  # how fast a commanded heading is turned to


class Motion(IntEnum):
    IDLE = 0  # on the ground (motors off or spinning): holds still
    GOTO = 1  # position controller toward goal_m
    LAND = 2  # horizontal controller toward goal_m, descend at land speed until touchdown
    VELOCITY = 3  # follow velocity_mps (GUIDED velocity control), within the speed limits


IDLE, GOTO, LAND, VELOCITY = (int(m) for m in Motion)  # plain ints: numpy compares an enum member far slower


@dataclass(frozen=True)
class PhysicsParams:
    """Per-vehicle arrays (shape (N,)) in SI units."""

    k_xy: np.ndarray  # 1/s, gain of desired velocity on horizontal position error
    k_z: np.ndarray  # 1/s, gain on vertical position error
    speed_xy_max_mps: np.ndarray
    speed_up_max_mps: np.ndarray
    speed_down_max_mps: np.ndarray
    land_speed_mps: np.ndarray
    vel_tau_s: np.ndarray  # first-order velocity response time constant
    batt_capacity_mah: np.ndarray
    batt_cells: np.ndarray
    power: energy.PowerArrays  # each vehicle's frame, for its propulsion power
    research_law: np.ndarray | None = None  # (N,) bool: the research's proportional law, else ArduCopter's
    accel_xy_mps2: np.ndarray | None = None  # WPNAV_ACCEL, for ArduCopter's law
    accel_z_mps2: np.ndarray | None = None  # WPNAV_ACCEL_Z
    land_speed_high_mps: np.ndarray | None = None  # LAND above land_alt_low_m (ArduCopter's law)
    land_alt_low_m: np.ndarray | None = None

    @cached_property
    def laws_in_use(self) -> tuple[bool, bool]:
        """(any vehicle on the research's law, any on ArduCopter's): fixed for these parameters."""
        if self.research_law is None:
            return True, False
        return bool(self.research_law.any()), not bool(self.research_law.all())

    def response_alpha(self, dt_s: float) -> np.ndarray:
        """How far the velocity moves toward its target in one step of dt_s (first-order response)."""
        cache = self.__dict__.setdefault("_alpha_by_dt", {})  # frozen, so kept beside the fields
        if dt_s not in cache:
            cache[dt_s] = 1.0 - np.exp(-dt_s / self.vel_tau_s)
        return cache[dt_s]

    @staticmethod
    def defaults(n: int) -> PhysicsParams:
        def full(value: float) -> np.ndarray:
            return np.full(n, value, dtype=float)

        return PhysicsParams(
            k_xy=full(0.15), k_z=full(1.0), speed_xy_max_mps=full(5.0), speed_up_max_mps=full(2.5),
            speed_down_max_mps=full(1.5), land_speed_mps=full(0.5), vel_tau_s=full(0.3),
            batt_capacity_mah=full(5000.0), batt_cells=full(4.0),
            power=energy.PowerArrays.of([energy.FRAMES[energy.FRAME_NAMES[0]]] * n),
        )


@dataclass(frozen=True)
class VehicleState:
    """True state of every vehicle; positions are local ENU metres about each vehicle's own home."""

    pos_m: np.ndarray  # (N, 3) east, north, up
    vel_mps: np.ndarray  # (N, 3)
    accel_mps2: np.ndarray  # (N, 3) last step's acceleration (drives attitude)
    yaw_rad: np.ndarray  # (N,) heading, 0 = north, clockwise positive
    on_ground: np.ndarray  # (N,) bool
    soc: np.ndarray  # (N,) battery state of charge 0..1
    current_a: np.ndarray  # (N,)
    voltage_v: np.ndarray  # (N,) at the terminals, under the present load
    consumed_mah: np.ndarray  # (N,)
    consumed_wh: np.ndarray  # (N,) energy delivered at the terminals

    @staticmethod
    def at_rest(n: int, params: PhysicsParams) -> VehicleState:
        zeros3 = np.zeros((n, 3))
        soc = np.ones(n)
        current_a, voltage_v = battery_load(soc, params.power.avionics_w, params.batt_cells)
        return VehicleState(
            pos_m=zeros3.copy(), vel_mps=zeros3.copy(), accel_mps2=zeros3.copy(), yaw_rad=np.zeros(n),
            on_ground=np.ones(n, dtype=bool), soc=soc, current_a=current_a, voltage_v=voltage_v,
            consumed_mah=np.zeros(n), consumed_wh=np.zeros(n),
        )


@dataclass(frozen=True)
class Command:
    motion: np.ndarray  # (N,) Motion values
    goal_m: np.ndarray  # (N, 3) ENU goal
    armed: np.ndarray  # (N,) bool
    speed_xy_mps: np.ndarray  # (N,) current horizontal speed limit (mission DO_CHANGE_SPEED may lower it)
    velocity_mps: np.ndarray | None = None  # (N, 3) ENU, for Motion.VELOCITY
    yaw_target_rad: np.ndarray | None = None  # (N,) heading to turn to; NaN: face the direction of travel
    yaw_rate_rps: np.ndarray | None = None  # (N,) turn at this rate; NaN: no rate command


def battery_load(soc: np.ndarray, power_w: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(current in A, terminal voltage in V) of each pack delivering power_w (energy.py's LiPo)."""
    open_v = energy.open_circuit_v(soc, cells)
    current_a = energy.pack_current_a(power_w, open_v, cells)
    return current_a, energy.terminal_v(open_v, current_a, cells)


def battery_power_w(vel_mps: np.ndarray, flying: np.ndarray, power: energy.PowerArrays) -> np.ndarray:
    """What each pack delivers: the avionics always, the propulsion (Zeng's model plus climb) while flying."""
    if not flying.any():
        return power.avionics_w
    speed_xy = np.hypot(vel_mps[:, 0], vel_mps[:, 1])
    shaft_w = energy.shaft_power_w(power, speed_xy, vel_mps[:, 2])
    return power.avionics_w + np.where(flying, shaft_w / power.drive_efficiency, 0.0)


def desired_velocity_mps(pos_m, goal_m, params: PhysicsParams, speed_xy_mps) -> np.ndarray:
    """The research's proportional position controller with speed clamps.

    The paper prints v = k (x - x_g); with positive gains that drives the vehicle away from its goal, so the
    converging sign v = k (x_g - x) is used here.
    """
    error = goal_m - pos_m
    v_des = np.empty_like(error)
    v_des[:, 0] = params.k_xy * error[:, 0]
    v_des[:, 1] = params.k_xy * error[:, 1]
    v_des[:, 2] = params.k_z * error[:, 2]
    horizontal = np.hypot(v_des[:, 0], v_des[:, 1])
    limit = np.minimum(speed_xy_mps, params.speed_xy_max_mps)
    scale = np.where(horizontal > limit, limit / np.maximum(horizontal, 1e-12), 1.0)
    v_des[:, :2] *= scale[:, None]
    v_des[:, 2] = np.clip(v_des[:, 2], -params.speed_down_max_mps, params.speed_up_max_mps)
    return v_des


def clamp_velocity_mps(velocity_mps, params: PhysicsParams, speed_xy_mps, which) -> np.ndarray:
    """A commanded velocity within the horizontal, climb and descent limits of the vehicles `which` selects."""
    v = np.array(velocity_mps, dtype=float)
    horizontal = np.hypot(v[:, 0], v[:, 1])
    limit = np.minimum(speed_xy_mps[which], params.speed_xy_max_mps[which])
    v[:, :2] *= np.where(horizontal > limit, limit / np.maximum(horizontal, 1e-12), 1.0)[:, None]
    v[:, 2] = np.clip(v[:, 2], -params.speed_down_max_mps[which], params.speed_up_max_mps[which])
    return v


def commanded_yaw_rad(yaw_rad, previous_rad, target_rad, rate_rps, dt_s: float) -> np.ndarray:
    """Heading where a yaw (turned to at YAW_RATE_MAX_RPS at most) or a yaw rate is commanded; else `yaw_rad`."""
    out = np.array(yaw_rad, dtype=float)
    has_target = ~np.isnan(target_rad)
    if has_target.any():  # at the commanded rate when there is one (CONDITION_YAW's speed), else the fastest
        error = (target_rad[has_target] - previous_rad[has_target] + math.pi) % (2 * math.pi) - math.pi
        rate = rate_rps[has_target]
        step = np.where(np.isnan(rate), YAW_RATE_MAX_RPS, np.minimum(np.abs(rate), YAW_RATE_MAX_RPS)) * dt_s
        out[has_target] = previous_rad[has_target] + np.clip(error, -step, step)
    has_rate = ~has_target & ~np.isnan(rate_rps)
    if has_rate.any():
        out[has_rate] = previous_rad[has_rate] + np.clip(rate_rps[has_rate], -YAW_RATE_MAX_RPS,
                                                          YAW_RATE_MAX_RPS) * dt_s
    return (out + math.pi) % (2 * math.pi) - math.pi


STOP_TAU_S = 0.5  # last metres of a leg: speed proportional to the distance left, so the stop does not chatter


def copter_velocity_mps(pos_m, goal_m, vel_mps, params: PhysicsParams, speed_xy_mps, which) -> np.ndarray:
    """ArduCopter's WPNav in outline: a trapezoid to the goal (accelerate at WPNAV_ACCEL, cruise at the leg's
    speed, brake so as to stop there), the same vertically with WPNAV_ACCEL_Z. The speed is the mission's
    (DO_CHANGE_SPEED may exceed WPNAV_SPEED, as on ArduCopter). The change asked of the first-order velocity
    response is kept to what the acceleration limit allows within its time constant."""
    error = goal_m - pos_m
    tau = params.vel_tau_s[which]
    distance_xy = np.hypot(error[:, 0], error[:, 1])
    toward = error[:, :2] / np.maximum(distance_xy, 1e-9)[:, None]
    # braking starts a response time early: the velocity follows its target tau late
    closing_xy = np.maximum(np.einsum("ij,ij->i", vel_mps[:, :2], toward), 0.0)
    braking_xy = np.maximum(distance_xy - closing_xy * tau, 0.0)
    accel_xy, accel_z = params.accel_xy_mps2[which], params.accel_z_mps2[which]
    speed = np.minimum.reduce([speed_xy_mps, np.sqrt(2.0 * accel_xy * braking_xy), distance_xy / STOP_TAU_S])
    target = np.empty_like(error)
    target[:, :2] = toward * speed[:, None]
    climb_max = np.where(error[:, 2] > 0, params.speed_up_max_mps[which], params.speed_down_max_mps[which])
    height = np.abs(error[:, 2])
    braking_z = np.maximum(height - np.maximum(vel_mps[:, 2] * np.sign(error[:, 2]), 0.0) * tau, 0.0)
    target[:, 2] = np.sign(error[:, 2]) * np.minimum.reduce([climb_max, np.sqrt(2.0 * accel_z * braking_z),
                                                             height / STOP_TAU_S])
    change = target - vel_mps
    change_xy = np.hypot(change[:, 0], change[:, 1])
    change[:, :2] *= np.minimum(1.0, accel_xy * tau / np.maximum(change_xy, 1e-9))[:, None]
    change[:, 2] = np.clip(change[:, 2], -accel_z * tau, accel_z * tau)
    return vel_mps + change


def goal_velocity_mps(state: VehicleState, cmd: Command, params: PhysicsParams,
                      to_goal: np.ndarray | None = None) -> np.ndarray:
    """The velocity each vehicle's law asks for toward its goal, each law computed only where it is in use (and
    ArduCopter's, the dearer, only for vehicles flying to a goal, `to_goal`: an idle one is held still by the
    step)."""
    research_in_use, copter_in_use = params.laws_in_use
    if not copter_in_use:
        return desired_velocity_mps(state.pos_m, cmd.goal_m, params, cmd.speed_xy_mps)
    v_des = desired_velocity_mps(state.pos_m, cmd.goal_m, params, cmd.speed_xy_mps) if research_in_use \
        else np.zeros_like(state.pos_m)
    if to_goal is None:
        to_goal = cmd.armed & ((cmd.motion == GOTO) | (cmd.motion == LAND))
    copter = to_goal & ~params.research_law if research_in_use else to_goal
    if not copter.any():
        return v_des
    v_des[copter] = copter_velocity_mps(state.pos_m[copter], cmd.goal_m[copter], state.vel_mps[copter], params,
                                        cmd.speed_xy_mps[copter], copter)
    return v_des


def land_speed_mps(height_m, params: PhysicsParams) -> np.ndarray:
    """LAND's descent: ArduCopter's law comes down at LAND_SPEED_HIGH above LAND_ALT_LOW, LAND_SPEED below."""
    if params.research_law is None:
        return params.land_speed_mps
    high = ~params.research_law & (height_m > params.land_alt_low_m)
    return np.where(high, params.land_speed_high_mps, params.land_speed_mps)


def step(state: VehicleState, cmd: Command, params: PhysicsParams, dt_s: float) -> VehicleState:
    # Written for few numpy calls: at 100 Hz and tens of vehicles each call's fixed cost is most of the time.
    motion = cmd.motion
    landing = motion == LAND
    idle = (motion == IDLE) | ~cmd.armed
    v_des = goal_velocity_mps(state, cmd, params, ~idle & (landing | (motion == GOTO)))
    if cmd.velocity_mps is not None:
        following = motion == VELOCITY
        if following.any():
            v_des[following] = clamp_velocity_mps(cmd.velocity_mps[following], params, cmd.speed_xy_mps, following)
    if landing.any():
        v_des[:, 2] = np.where(landing, -land_speed_mps(state.pos_m[:, 2], params), v_des[:, 2])
    v_des[idle] = 0.0

    alpha = params.response_alpha(dt_s)
    vel = state.vel_mps + alpha[:, None] * (v_des - state.vel_mps)
    pos = state.pos_m + vel * dt_s

    # The ground stops descent; a vehicle idling on the ground does not slide.
    touching = pos[:, 2] <= 0.0
    on_ground = touching & (landing | idle | (v_des[:, 2] <= 0.0))
    if touching.any():
        pos[:, 2] = np.maximum(pos[:, 2], 0.0)
        vel[:, 2] = np.where(touching, np.maximum(vel[:, 2], 0.0), vel[:, 2])
        vel[on_ground] = 0.0
        pos = np.where((on_ground & idle)[:, None], state.pos_m, pos)
        pos[on_ground, 2] = 0.0

    accel = (vel - state.vel_mps) / dt_s
    speed_xy = np.hypot(vel[:, 0], vel[:, 1])
    yaw = np.where(speed_xy > 0.3, np.arctan2(vel[:, 0], vel[:, 1]), state.yaw_rad)
    if cmd.yaw_target_rad is not None and not (np.isnan(cmd.yaw_target_rad).all() and np.isnan(cmd.yaw_rate_rps).all()):
        yaw = commanded_yaw_rad(yaw, state.yaw_rad, cmd.yaw_target_rad, cmd.yaw_rate_rps, dt_s)

    return VehicleState(
        pos_m=pos, vel_mps=vel, accel_mps2=accel, yaw_rad=yaw, on_ground=on_ground, soc=state.soc,
        current_a=state.current_a, voltage_v=state.voltage_v, consumed_mah=state.consumed_mah,
        consumed_wh=state.consumed_wh,
    )


def drain(state: VehicleState, params: PhysicsParams, armed: np.ndarray, dt_s: float) -> VehicleState:
    """The packs over the last dt_s: each delivers its vehicle's power at the present speed and climb (the world
    calls this at BATTERY_PERIOD_S, as ArduPilot's battery monitor reads its sensor at 10 Hz; the kinematics step
    at 100 Hz would spend a third of its time here)."""
    power_w = battery_power_w(state.vel_mps, armed & ~state.on_ground, params.power)
    current_a, voltage_v = battery_load(state.soc, power_w, params.batt_cells)
    used_mah = current_a * (dt_s / 3.6)
    return replace(state, soc=np.maximum(state.soc - used_mah / params.batt_capacity_mah, 0.0), current_a=current_a,
                   voltage_v=voltage_v, consumed_mah=state.consumed_mah + used_mah,
                   consumed_wh=state.consumed_wh + voltage_v * current_a * (dt_s / 3600.0))


def attitude_rad(state: VehicleState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Roll and pitch a multirotor needs for its acceleration, and its yaw (small-angle point-mass model)."""
    cos_y, sin_y = np.cos(state.yaw_rad), np.sin(state.yaw_rad)
    a_forward = state.accel_mps2[:, 1] * cos_y + state.accel_mps2[:, 0] * sin_y
    a_right = state.accel_mps2[:, 0] * cos_y - state.accel_mps2[:, 1] * sin_y
    pitch = -np.arctan2(a_forward, GRAVITY_MPS2)
    roll = np.arctan2(a_right, GRAVITY_MPS2)
    return roll, pitch, state.yaw_rad


def gps_noise_m(rng: np.random.Generator, n: int, sigma_xy_m: float, sigma_z_m: float) -> np.ndarray:
    """Independent Gaussian position error per vehicle; deterministic for a seeded generator."""
    if sigma_xy_m <= 0 and sigma_z_m <= 0:
        return np.zeros((n, 3))
    noise = rng.standard_normal((n, 3))
    noise[:, :2] *= sigma_xy_m
    noise[:, 2] *= sigma_z_m
    return noise
