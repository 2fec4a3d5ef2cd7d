"""The geometry of the mission items that fly a pattern, and how long an item holds (pure). Which items the
simulated copter takes at upload is ArduCopter's table, missions.firmware."""

from __future__ import annotations

import math

import numpy as np

from missions.firmware import NAV_SPLINE_WAYPOINT
from missions.model import MavCmd, MissionItem

CIRCLE_RATE_DPS = 20.0  # ArduCopter's CIRCLE_RATE default
CIRCLE_RADIUS_MIN_M = 1.0


def holds_s(item: MissionItem) -> float:
    """Seconds a navigation item waits once reached (LOITER_TIME's time, a waypoint's hold), 0 for none."""
    if item.command == MavCmd.NAV_LOITER_TIME or item.command in (MavCmd.NAV_WAYPOINT, NAV_SPLINE_WAYPOINT):
        return max(0.0, item.p1) if math.isfinite(item.p1) else 0.0
    return 0.0


def turns(item: MissionItem) -> tuple[float, float]:
    """NAV_LOITER_TURNS: (turns, signed radius in metres: negative counter-clockwise), as ArduCopter reads them."""
    count = max(0.0, item.p1) if math.isfinite(item.p1) else 0.0
    radius = item.p3 if math.isfinite(item.p3) and item.p3 != 0 else 10.0
    return count, math.copysign(max(abs(radius), CIRCLE_RADIUS_MIN_M), radius)


def circle_velocity_mps(pos_m: np.ndarray, center_m: np.ndarray, radius_m: float, k_radial: float,
                        k_z: float, rate_dps: float = CIRCLE_RATE_DPS) -> np.ndarray:
    """Velocity that goes round the circle (clockwise seen from above for a positive radius) at rate_dps
    (CIRCLE_RATE), pulled onto it radially and to the centre's altitude."""
    offset = pos_m[:2] - center_m[:2]
    distance = float(np.hypot(*offset))
    outward = offset / distance if distance > 1e-6 else np.array([0.0, 1.0])
    clockwise = np.array([outward[1], -outward[0]])  # east, north: clockwise tangent when north is up
    direction = 1.0 if radius_m > 0 else -1.0
    speed = math.radians(abs(rate_dps)) * abs(radius_m)
    horizontal = direction * speed * clockwise + k_radial * (abs(radius_m) - distance) * outward
    return np.array([horizontal[0], horizontal[1], k_z * (center_m[2] - pos_m[2])])


def angle_about(pos_m: np.ndarray, center_m: np.ndarray) -> float:
    """Bearing of the vehicle from the centre (radians, clockwise from north)."""
    return math.atan2(pos_m[0] - center_m[0], pos_m[1] - center_m[1])
