"""The mission model shared by the SITL, the client and the file formats.

Numbers are MAVLink's (common.xml) so items cross the wire unchanged; this module stays stdlib-only so the
mission library can be used without pymavlink.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum


class MavCmd(IntEnum):
    NAV_WAYPOINT = 16
    NAV_LOITER_UNLIM = 17
    NAV_LOITER_TURNS = 18
    NAV_LOITER_TIME = 19
    NAV_RETURN_TO_LAUNCH = 20
    NAV_LAND = 21
    NAV_TAKEOFF = 22
    DO_JUMP = 177
    DO_CHANGE_SPEED = 178
    DO_SET_MODE = 176
    DO_SET_MISSION_CURRENT = 224
    COMPONENT_ARM_DISARM = 400
    MISSION_START = 300
    SET_MESSAGE_INTERVAL = 511
    REQUEST_MESSAGE = 512
    REQUEST_AUTOPILOT_CAPABILITIES = 520


class Frame(IntEnum):
    GLOBAL = 0
    LOCAL_NED = 1
    MISSION = 2
    GLOBAL_RELATIVE_ALT = 3
    LOCAL_ENU = 4
    GLOBAL_INT = 5
    GLOBAL_RELATIVE_ALT_INT = 6
    GLOBAL_TERRAIN_ALT = 10
    GLOBAL_TERRAIN_ALT_INT = 11


class MissionType(IntEnum):
    MISSION = 0
    FENCE = 1
    RALLY = 2


#: Frames whose altitude is above mean sea level; the others used here are relative to home.
AMSL_FRAMES = frozenset({Frame.GLOBAL, Frame.GLOBAL_INT})
RELATIVE_FRAMES = frozenset({Frame.GLOBAL_RELATIVE_ALT, Frame.GLOBAL_RELATIVE_ALT_INT})
#: Commands whose x/y/z are a position.
NAV_COMMANDS = frozenset({
    MavCmd.NAV_WAYPOINT, MavCmd.NAV_LOITER_UNLIM, MavCmd.NAV_LOITER_TURNS, MavCmd.NAV_LOITER_TIME,
    MavCmd.NAV_RETURN_TO_LAUNCH, MavCmd.NAV_LAND, MavCmd.NAV_TAKEOFF,
})


@dataclass(frozen=True)
class MissionItem:
    """One MISSION_ITEM_INT in float form: lat/lon in degrees, alt in metres in the item's frame."""

    seq: int
    command: int
    frame: int = Frame.GLOBAL_RELATIVE_ALT_INT
    p1: float = 0.0
    p2: float = 0.0
    p3: float = 0.0
    p4: float = 0.0
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    alt_m: float = 0.0
    autocontinue: bool = True
    current: bool = False
    mission_type: int = MissionType.MISSION

    def same_as(self, other: MissionItem, tol_deg: float = 1e-7, tol_m: float = 1e-3) -> bool:
        """Equality after a wire round trip: lat/lon are 1e-7 degree integers, params are float32."""
        def close(a: float, b: float, tol: float) -> bool:
            return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol

        params_ok = all(close(a, b, max(1e-6, 1e-6 * abs(a)))
                        for a, b in zip(self.params(), other.params(), strict=True))
        return (self.seq == other.seq and self.command == other.command and self.frame == other.frame
                and bool(self.autocontinue) == bool(other.autocontinue)
                and self.mission_type == other.mission_type and params_ok
                and close(self.lat_deg, other.lat_deg, tol_deg) and close(self.lon_deg, other.lon_deg, tol_deg)
                and close(self.alt_m, other.alt_m, tol_m))

    def params(self) -> tuple[float, float, float, float]:
        return (self.p1, self.p2, self.p3, self.p4)
