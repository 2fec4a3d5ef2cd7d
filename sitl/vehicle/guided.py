"""GUIDED setpoints as ArduCopter reads SET_POSITION_TARGET_LOCAL_NED and _GLOBAL_INT (pure).

The type mask says which of position, velocity, acceleration, yaw and yaw rate the sender means: a group counts
only when none of its three bits is set to "ignore" (ArduCopter's rule; a partly ignored group is used whole).
Position with or without velocity flies to the position; velocity or acceleration alone is velocity control,
which stops after VELOCITY_TIMEOUT_S without a new setpoint; everything ignored stops the vehicle where it is.

Local frames: LOCAL_NED about home (ArduPilot's EKF origin is home here), LOCAL_OFFSET_NED about the vehicle,
BODY_NED and BODY_OFFSET_NED about the vehicle with x forward and y right (position, velocity and acceleration
rotated by the heading). Global frames: GLOBAL and GLOBAL_INT altitude above mean sea level, the relative and
terrain frames above home (the simulated ground is flat at home's altitude).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

POS_IGNORE = 0b111
VEL_IGNORE = 0b111 << 3
ACC_IGNORE = 0b111 << 6
YAW_IGNORE = 1 << 10
YAW_RATE_IGNORE = 1 << 11
VELOCITY_TIMEOUT_S = 3.0  # ArduCopter GUIDED: velocity and acceleration control stop after this without updates

LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED = 1, 7, 8, 9
LOCAL_FRAMES = frozenset({LOCAL_NED, LOCAL_OFFSET_NED, BODY_NED, BODY_OFFSET_NED})
GLOBAL_AMSL_FRAMES = frozenset({0, 5})  # MAV_FRAME_GLOBAL, MAV_FRAME_GLOBAL_INT
GLOBAL_RELATIVE_FRAMES = frozenset({3, 6, 10, 11})  # GLOBAL_RELATIVE_ALT(_INT), GLOBAL_TERRAIN_ALT(_INT)


@dataclass(frozen=True)
class Setpoint:
    """What the vehicle is asked to do, in ENU metres about home; None where the mask ignores it."""

    pos_m: np.ndarray | None = None
    vel_mps: np.ndarray | None = None
    acc_mps2: np.ndarray | None = None
    yaw_rad: float | None = None  # heading, 0 = north, clockwise positive
    yaw_rate_rps: float | None = None

    @property
    def is_velocity_control(self) -> bool:
        return self.pos_m is None and (self.vel_mps is not None or self.acc_mps2 is not None)


def _used(mask: int, bits: int) -> bool:
    return mask & bits != bits


def _ned_to_enu(north: float, east: float, down: float) -> np.ndarray:
    return np.array([east, north, -down], dtype=float)


def _body_to_enu(forward: float, right: float, down: float, heading_rad: float) -> np.ndarray:
    """Body x forward, y right (heading 0 = north, clockwise) to ENU."""
    north = forward * math.cos(heading_rad) - right * math.sin(heading_rad)
    east = forward * math.sin(heading_rad) + right * math.cos(heading_rad)
    return np.array([east, north, -down], dtype=float)


def _yaw(mask: int, yaw: float, yaw_rate: float, frame: int, heading_rad: float) -> tuple[float | None, float | None]:
    yaw_rad = float(yaw) if _used(mask, YAW_IGNORE) and math.isfinite(yaw) else None
    if yaw_rad is not None and frame in (BODY_NED, BODY_OFFSET_NED):
        yaw_rad += heading_rad  # ArduCopter takes a body-frame yaw as relative to the heading
    rate = float(yaw_rate) if _used(mask, YAW_RATE_IGNORE) and math.isfinite(yaw_rate) else None
    return yaw_rad, rate


def local_setpoint(frame: int, mask: int, xyz: tuple, vel: tuple, acc: tuple, yaw: float, yaw_rate: float,
                   here_m: np.ndarray, heading_rad: float) -> Setpoint | None:
    """A SET_POSITION_TARGET_LOCAL_NED in ENU about home; None for a frame ArduCopter does not take here or for
    values that are not finite."""
    if frame not in LOCAL_FRAMES:
        return None
    body = frame in (BODY_NED, BODY_OFFSET_NED)

    def to_enu(values) -> np.ndarray | None:
        if not all(math.isfinite(v) for v in values):
            raise ValueError
        return _body_to_enu(*values, heading_rad) if body else _ned_to_enu(*values)

    try:
        pos = to_enu(xyz) if _used(mask, POS_IGNORE) else None
        velocity = to_enu(vel) if _used(mask, VEL_IGNORE) else None
        accel = to_enu(acc) if _used(mask, ACC_IGNORE) else None
    except ValueError:
        return None
    if pos is not None and frame != LOCAL_NED:
        pos = pos + here_m
    yaw_rad, rate = _yaw(mask, yaw, yaw_rate, frame, heading_rad)
    return Setpoint(pos, velocity, accel, yaw_rad, rate)


def global_setpoint(frame: int, mask: int, pos_m: np.ndarray | None, vel: tuple, acc: tuple, yaw: float,
                    yaw_rate: float) -> Setpoint | None:
    """A SET_POSITION_TARGET_GLOBAL_INT whose position the caller has already put in ENU about home (None when
    the mask ignores it); velocity and acceleration are NED. None for a frame ArduCopter does not take."""
    if frame not in GLOBAL_AMSL_FRAMES | GLOBAL_RELATIVE_FRAMES:
        return None
    if not all(math.isfinite(v) for v in (*vel, *acc)) or (pos_m is not None and not np.isfinite(pos_m).all()):
        return None
    velocity = _ned_to_enu(*vel) if _used(mask, VEL_IGNORE) else None
    accel = _ned_to_enu(*acc) if _used(mask, ACC_IGNORE) else None
    yaw_rad, rate = _yaw(mask, yaw, yaw_rate, frame, 0.0)
    return Setpoint(pos_m if _used(mask, POS_IGNORE) else None, velocity, accel, yaw_rad, rate)


def position_used(mask: int) -> bool:
    return _used(mask, POS_IGNORE)
