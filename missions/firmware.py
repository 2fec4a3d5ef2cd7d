"""What the simulated ArduCopter takes at mission upload (pure): NAC's SITL refuses what this table refuses, and
`nac-ground mission validate` says so before anything is sent (missions.validate's `firmware`).

ArduCopter's AUTO flies the navigation items below, runs the DO and CONDITION items between them, and takes the
items that act on hardware a simulation does not have (cameras, relays, grippers, parachutes, scripts), as
ArduCopter takes them with that hardware absent. One difference: ArduPilot's mission library also stores items only
a plane flies (NAV_LOITER_TO_ALT 31, NAV_CONTINUE_AND_CHANGE_ALT 30, NAV_ALTITUDE_WAIT 83) and a copter skips them in
flight; the SITL refuses them at upload (MAV_MISSION_UNSUPPORTED) instead, so that a mission says what it does.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from missions.model import Frame, MavCmd, MissionItem, MissionType

FIRMWARE = "ArduCopter (as NAC's SITL flies it)"
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
POLYGON_VERTICES = frozenset({MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION, MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION})
RALLY_COMMANDS = frozenset({MavCmd.NAV_RALLY_POINT})


def arducopter_refusal(item: MissionItem, mission_type: int) -> str | None:
    """The MAV_MISSION_RESULT name for an item the copter refuses at upload, None when it takes it."""
    if mission_type == MissionType.FENCE:
        if item.command not in FENCE_COMMANDS:
            return "MAV_MISSION_UNSUPPORTED"
        if item.command in POLYGON_VERTICES and not (math.isfinite(item.p1) and item.p1 >= 3 and item.p1 % 1 == 0):
            return "MAV_MISSION_INVALID_PARAM1"  # a polygon's vertex count: 3 or more (AC_PolyFence_loader)
        return None
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


@dataclass(frozen=True)
class Firmware:
    """A vehicle's firmware as a mission validator needs it: its name and what it refuses at upload."""

    name: str
    refusal: Callable[[MissionItem, int], str | None]


ARDUCOPTER = Firmware(FIRMWARE, arducopter_refusal)
FIRMWARES = {"arducopter": ARDUCOPTER}  # `nac-ground mission validate --firmware`; "any": no firmware's table
