"""The pilot's sticks as ArduCopter reads them from RC_CHANNELS_OVERRIDE (pure).

Channels 1-4 are roll, pitch, throttle and yaw (AETR, ArduCopter's default RCMAP), 1000-2000 µs. In the
pilot-controlled modes (LOITER, POSHOLD, ALT_HOLD) the sticks ask for a velocity: forward and right up to
LOIT_SPEED, climb and descent up to PILOT_SPEED_UP / _DN with the throttle's mid-stick dead zone, and a yaw rate.
An override lasts RC_OVERRIDE_TIME (3 s) after its last message; a 0 releases a channel and 65535 leaves it
as it was, as the message's definition says.
"""

from __future__ import annotations

import math

import numpy as np

CHANNELS = 16
CENTRE_US = 1500
THROTTLE_LOW_US = 1000  # what a copter's receiver gives with no pilot: sticks centred, throttle down
STICK_DEAD_ZONE_US = 20  # RCn_DZ
THROTTLE_DEAD_ZONE_US = 100  # THR_DZ: mid-throttle holds altitude
OVERRIDE_TIMEOUT_S = 3.0  # RC_OVERRIDE_TIME
YAW_RATE_MAX_DPS = 90.0
RELEASE, IGNORE = 0, 65535


def idle_channels() -> np.ndarray:
    channels = np.full(CHANNELS, CENTRE_US, dtype=int)
    channels[2] = THROTTLE_LOW_US
    return channels


def apply_override(current: np.ndarray, overridden: np.ndarray, values: list[int]) -> None:
    """Update one vehicle's channels and which of them are overridden, in place."""
    idle = idle_channels()
    for k, value in enumerate(values[:CHANNELS]):
        if value == IGNORE:
            continue
        if value == RELEASE or not 800 <= value <= 2200:
            current[k], overridden[k] = idle[k], False
        else:
            current[k], overridden[k] = value, True


def _stick(value_us: float, dead_zone_us: float) -> float:
    """-1..1 from a PWM value, 0 inside the dead zone about the centre."""
    offset = value_us - CENTRE_US
    if abs(offset) <= dead_zone_us:
        return 0.0
    return max(-1.0, min(1.0, (offset - math.copysign(dead_zone_us, offset)) / (500.0 - dead_zone_us)))


def stick_command(channels: np.ndarray, throttle_overridden: bool, heading_rad: float, speed_xy_mps: float,
                  climb_mps: float, descent_mps: float) -> tuple[np.ndarray, float]:
    """The ENU velocity and the yaw rate (rad/s, clockwise) the sticks ask for. A throttle nobody overrides
    holds the altitude, as mid-throttle does: there is no receiver here to give the pilot's."""
    right = _stick(channels[0], STICK_DEAD_ZONE_US)
    forward = -_stick(channels[1], STICK_DEAD_ZONE_US)  # pitch stick forward is a low PWM
    throttle = _stick(channels[2], THROTTLE_DEAD_ZONE_US) if throttle_overridden else 0.0
    yaw = _stick(channels[3], STICK_DEAD_ZONE_US)
    north = speed_xy_mps * (forward * math.cos(heading_rad) - right * math.sin(heading_rad))
    east = speed_xy_mps * (forward * math.sin(heading_rad) + right * math.cos(heading_rad))
    up = throttle * (climb_mps if throttle > 0 else descent_mps)
    return np.array([east, north, up]), math.radians(YAW_RATE_MAX_DPS) * yaw
