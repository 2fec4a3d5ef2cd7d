"""Which mission items the simulated copter takes, and the geometry of the ones that fly a pattern (pure).

ArduCopter's AUTO flies the navigation items below, runs the DO and CONDITION items between them, and refuses at
upload (MAV_MISSION_UNSUPPORTED) only what its mission library does not know. Items that act on hardware a
simulation does not have (cameras, relays, grippers, parachutes, scripts) are accepted and acknowledged with no
effect, as ArduCopter would with that hardware absent.
"""

from __future__ import annotations

import math

import numpy as np

from missions.model import Frame, MavCmd, MissionItem, MissionType

NAV_SPLINE_WAYPOINT, NAV_ARC_WAYPOINT, NAV_DELAY = 82, 36, 93
NAV_VTOL_TAKEOFF, NAV_VTOL_LAND = 84, 85
WAYPOINTS = frozenset({MavCmd.NAV_WAYPOINT, NAV_SPLINE_WAYPOINT, NAV_ARC_WAYPOINT})
TAKEOFFS = frozenset({MavCmd.NAV_TAKEOFF, NAV_VTOL_TAKEOFF})
LANDINGS = frozenset({MavCmd.NAV_LAND, NAV_VTOL_LAND})
#: navigation items, flown one at a time
NAV_FLOWN = WAYPOINTS | TAKEOFFS | LANDINGS | frozenset({
    MavCmd.NAV_LOITER_UNLIM, MavCmd.NAV_LOITER_TURNS, MavCmd.NAV_LOITER_TIME, MavCmd.NAV_RETURN_TO_LAUNCH,
    NAV_DELAY})
DO_SET_HOME, DO_SET_SERVO = 179, 183
DO_SET_ROI_LOCATION, DO_SET_ROI_NONE, DO_SET_ROI, DO_FENCE_ENABLE = 195, 197, 201, 207
JUMP_TAG, DO_JUMP_TAG = 600, 601
#: DO and CONDITION items that change what the simulated copter does
DO_ACTED = frozenset({MavCmd.DO_CHANGE_SPEED, MavCmd.DO_JUMP, DO_JUMP_TAG, JUMP_TAG, MavCmd.CONDITION_YAW,
                      DO_SET_ROI, DO_SET_ROI_LOCATION, DO_SET_ROI_NONE, DO_SET_SERVO, DO_FENCE_ENABLE, DO_SET_HOME})
#: accepted and passed over: their hardware or timing has no counterpart here
DO_NO_EFFECT = frozenset({
    112, 114,  # CONDITION_DELAY, CONDITION_DISTANCE (they delay DO items, which change nothing here)
    181, 182, 184, 188, 189,  # SET_RELAY, REPEAT_RELAY, REPEAT_SERVO, RETURN_PATH_START, LAND_START
    202, 203, 204, 205, 206, 208, 211, 212, 215, 216, 217, 218, 222, 223,  # cameras, mount, fence, parachute..
    1000, 2000, 2001, 2500, 2501, 42600,  # gimbal manager, image and video capture, winch
})
LOCATION_FREE = frozenset({MavCmd.NAV_RETURN_TO_LAUNCH, NAV_DELAY}) | DO_ACTED | DO_NO_EFFECT
SUPPORTED_FRAMES = frozenset({Frame.GLOBAL, Frame.GLOBAL_RELATIVE_ALT, Frame.GLOBAL_INT, Frame.GLOBAL_RELATIVE_ALT_INT,
                              Frame.GLOBAL_TERRAIN_ALT, Frame.GLOBAL_TERRAIN_ALT_INT, Frame.MISSION})
FENCE_COMMANDS = frozenset({
    MavCmd.NAV_FENCE_RETURN_POINT, MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION,
    MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION, MavCmd.NAV_FENCE_CIRCLE_INCLUSION, MavCmd.NAV_FENCE_CIRCLE_EXCLUSION,
})
RALLY_COMMANDS = frozenset({MavCmd.NAV_RALLY_POINT})
CIRCLE_RATE_DPS = 20.0  # ArduCopter's CIRCLE_RATE default: loiter turns go round at this rate
CIRCLE_RADIUS_MIN_M = 1.0


def validate_item(item: MissionItem, mission_type: int) -> str | None:
    """The MAV_MISSION_RESULT name for an item the copter refuses at upload, None when it takes it."""
    if mission_type == MissionType.FENCE:
        return None if item.command in FENCE_COMMANDS else "MAV_MISSION_UNSUPPORTED"
    if mission_type == MissionType.RALLY:
        return None if item.command in RALLY_COMMANDS else "MAV_MISSION_UNSUPPORTED"
    if item.seq == 0:
        return None  # home slot: ArduPilot ignores what is uploaded there
    if item.command not in NAV_FLOWN | DO_ACTED | DO_NO_EFFECT:
        return "MAV_MISSION_UNSUPPORTED"
    if item.command in LOCATION_FREE:
        return None
    if item.frame not in SUPPORTED_FRAMES:
        return "MAV_MISSION_UNSUPPORTED_FRAME"
    if not (math.isfinite(item.lat_deg) and -90 <= item.lat_deg <= 90):
        return "MAV_MISSION_INVALID_PARAM5_X"
    if not (math.isfinite(item.lon_deg) and -180 <= item.lon_deg <= 180):
        return "MAV_MISSION_INVALID_PARAM6_Y"
    if not math.isfinite(item.alt_m):
        return "MAV_MISSION_INVALID_PARAM7"
    return None


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
                        k_z: float) -> np.ndarray:
    """Velocity that goes round the circle (clockwise seen from above for a positive radius) at CIRCLE_RATE,
    pulled onto it radially and to the centre's altitude."""
    offset = pos_m[:2] - center_m[:2]
    distance = float(np.hypot(*offset))
    outward = offset / distance if distance > 1e-6 else np.array([0.0, 1.0])
    clockwise = np.array([outward[1], -outward[0]])  # east, north: clockwise tangent when north is up
    direction = 1.0 if radius_m > 0 else -1.0
    speed = math.radians(CIRCLE_RATE_DPS) * abs(radius_m)
    horizontal = direction * speed * clockwise + k_radial * (abs(radius_m) - distance) * outward
    return np.array([horizontal[0], horizontal[1], k_z * (center_m[2] - pos_m[2])])


def angle_about(pos_m: np.ndarray, center_m: np.ndarray) -> float:
    """Bearing of the vehicle from the centre (radians, clockwise from north)."""
    return math.atan2(pos_m[0] - center_m[0], pos_m[1] - center_m[1])
