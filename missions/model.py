"""The mission model shared by the SITL, the client and the file formats.

Numbers are MAVLink's (common.xml) so items cross the wire unchanged; this module stays stdlib-only so the
mission library can be used without pymavlink.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass, field
from enum import IntEnum
from typing import Any


class MavCmd(IntEnum):
    NAV_WAYPOINT = 16
    NAV_LOITER_UNLIM = 17
    NAV_LOITER_TURNS = 18
    NAV_LOITER_TIME = 19
    NAV_RETURN_TO_LAUNCH = 20
    NAV_LAND = 21
    NAV_TAKEOFF = 22
    CONDITION_DELAY = 112
    CONDITION_CHANGE_ALT = 113
    CONDITION_DISTANCE = 114
    CONDITION_YAW = 115
    DO_JUMP = 177
    DO_CHANGE_SPEED = 178
    DO_SET_MODE = 176
    DO_SET_MISSION_CURRENT = 224
    COMPONENT_ARM_DISARM = 400
    MISSION_START = 300
    SET_MESSAGE_INTERVAL = 511
    REQUEST_MESSAGE = 512
    REQUEST_AUTOPILOT_CAPABILITIES = 520
    NAV_FENCE_RETURN_POINT = 5000
    NAV_FENCE_POLYGON_VERTEX_INCLUSION = 5001
    NAV_FENCE_POLYGON_VERTEX_EXCLUSION = 5002
    NAV_FENCE_CIRCLE_INCLUSION = 5003
    NAV_FENCE_CIRCLE_EXCLUSION = 5004
    NAV_RALLY_POINT = 5100


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


#: MAVLink commands a mission file may hold (common.xml numbers); the SITL flies a subset of them, a real
#: ArduPilot more, so a file is refused only for a number no GCS would write.
COMMAND_NAMES: dict[int, str] = {
    16: "NAV_WAYPOINT", 17: "NAV_LOITER_UNLIM", 18: "NAV_LOITER_TURNS", 19: "NAV_LOITER_TIME",
    20: "NAV_RETURN_TO_LAUNCH", 21: "NAV_LAND", 22: "NAV_TAKEOFF", 31: "NAV_LOITER_TO_ALT",
    82: "NAV_SPLINE_WAYPOINT", 84: "NAV_VTOL_TAKEOFF", 85: "NAV_VTOL_LAND", 93: "NAV_DELAY",
    94: "NAV_PAYLOAD_PLACE", 112: "CONDITION_DELAY", 113: "CONDITION_CHANGE_ALT", 114: "CONDITION_DISTANCE",
    115: "CONDITION_YAW", 177: "DO_JUMP", 178: "DO_CHANGE_SPEED", 179: "DO_SET_HOME", 181: "DO_SET_RELAY",
    182: "DO_REPEAT_RELAY", 183: "DO_SET_SERVO", 184: "DO_REPEAT_SERVO", 189: "DO_LAND_START",
    195: "DO_SET_ROI_LOCATION", 197: "DO_SET_ROI_NONE", 201: "DO_SET_ROI", 203: "DO_DIGICAM_CONTROL",
    205: "DO_MOUNT_CONTROL", 206: "DO_SET_CAM_TRIGG_DIST", 211: "DO_GRIPPER", 2000: "IMAGE_START_CAPTURE",
    2001: "IMAGE_STOP_CAPTURE", 2500: "VIDEO_START_CAPTURE", 2501: "VIDEO_STOP_CAPTURE",
    3000: "DO_VTOL_TRANSITION", 5000: "NAV_FENCE_RETURN_POINT", 5001: "NAV_FENCE_POLYGON_VERTEX_INCLUSION",
    5002: "NAV_FENCE_POLYGON_VERTEX_EXCLUSION", 5003: "NAV_FENCE_CIRCLE_INCLUSION",
    5004: "NAV_FENCE_CIRCLE_EXCLUSION", 5100: "NAV_RALLY_POINT",
}
FENCE_COMMANDS = frozenset({5000, 5001, 5002, 5003, 5004})
RALLY_COMMANDS = frozenset({5100})


def command_name(command: int) -> str:
    return COMMAND_NAMES.get(command, f"command {command}")


def frame_name(frame: int) -> str:
    try:
        return Frame(frame).name
    except ValueError:
        return f"frame {frame}"


@dataclass(frozen=True)
class PlannedHome:
    """Where the mission was planned from; altitude above mean sea level (QGC's plannedHomePosition)."""

    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(frozen=True)
class PlanInfo:
    """Plan-level .plan fields MAVLink does not carry, kept so a file reads back as it was written."""

    ground_station: str = "NAC"
    firmware_type: int = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA: QGC then shows ArduPilot's commands and modes
    vehicle_type: int = 2  # MAV_TYPE_QUADROTOR
    cruise_speed_mps: float = 15.0
    hover_speed_mps: float = 5.0
    global_plan_altitude_mode: int | None = None  # QGC 4.x writes it; older files lack it


#: QGC's per-item altitude keys, kept as read because QGC recomputes params[6] from them on load.
PLAN_ALTITUDE_KEYS = ("Altitude", "AltitudeMode", "AMSLAltAboveTerrain")


@dataclass(frozen=True)
class PlanItemInfo:
    """Per-item .plan fields with no MAVLink counterpart."""

    do_jump_id: int
    altitude_keys: dict[str, Any] = field(default_factory=dict)  # subset of PLAN_ALTITUDE_KEYS, raw JSON values


def _same_value(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


def _identical(a: MissionItem, b: MissionItem) -> bool:
    """Field-for-field equality where NaN equals NaN (dataclass == says NaN != NaN)."""
    return all(_same_value(x, y) for x, y in zip(astuple(a), astuple(b), strict=True))


@dataclass
class Mission:
    """A mission as a file holds it: planned home, the items proper (seq 1..n), fence and rally (seq 0..).

    Item 0 of an ArduPilot mission is home, so `items` starts at seq 1 and `to_wire` adds the home slot.
    """

    home: PlannedHome | None = None
    items: list[MissionItem] = field(default_factory=list)
    fence: list[MissionItem] = field(default_factory=list)
    rally: list[MissionItem] = field(default_factory=list)
    plan: PlanInfo = field(default_factory=PlanInfo)
    #: .plan details by item seq; items without an entry are written with derived values
    item_info: dict[int, PlanItemInfo] = field(default_factory=dict)
    #: row 0's CURRENT flag in a QGC WPL file (MAVProxy writes 1, ArduPilot's own test missions 0), kept as read
    home_current: bool = True
    #: where each (mission_type, seq) was read from ("item 3 (doJumpId 3)", "line 5"), for error messages
    origins: dict[tuple[int, int], str] = field(default_factory=dict, compare=False, repr=False)
    #: what the reader did that the file did not say outright (a survey's stored items read in its place, rows
    #: renumbered), one sentence each, for the commands to print once
    notes: list[str] = field(default_factory=list, compare=False, repr=False)

    def where(self, mission_type: int, seq: int) -> str:
        found = self.origins.get((int(mission_type), seq))
        if found:
            return found
        if mission_type == MissionType.MISSION and seq == 0:
            return "planned home"
        if mission_type == MissionType.FENCE:
            return f"fence item {seq}"
        if mission_type == MissionType.RALLY:
            return f"rally item {seq}"
        info = self.item_info.get(seq)
        return f"item {seq}" + (f" (doJumpId {info.do_jump_id})" if info else "")

    def to_wire(self) -> list[MissionItem]:
        """The MISSION list a GCS uploads to ArduPilot: item 0 = planned home (AMSL, zeros if none), then items."""
        for k, item in enumerate(self.items, 1):
            if item.seq != k:
                raise ValueError(f"mission items must be numbered 1..{len(self.items)}: "
                                 f"item {k} in the list has seq {item.seq}")
        h = self.home
        home_item = MissionItem(0, MavCmd.NAV_WAYPOINT, Frame.GLOBAL, lat_deg=h.lat_deg if h else 0.0,
                                lon_deg=h.lon_deg if h else 0.0, alt_m=h.alt_m if h else 0.0)
        return [home_item, *self.items]

    @classmethod
    def from_wire(cls, items: list[MissionItem], fence: list[MissionItem] | None = None,
                  rally: list[MissionItem] | None = None) -> Mission:
        """Inverse of to_wire: item 0 becomes the planned home (none when it is all zeros)."""
        home = None
        if items and (items[0].lat_deg != 0.0 or items[0].lon_deg != 0.0):
            home = PlannedHome(items[0].lat_deg, items[0].lon_deg, items[0].alt_m)
        return cls(home=home, items=list(items[1:]), fence=list(fence or []), rally=list(rally or []))

    def same_items_as(self, other: Mission) -> bool:
        """Mission, fence and rally items equal within what a MAVLink round trip keeps (MissionItem.same_as)."""
        return all(len(a) == len(b) and all(x.same_as(y) for x, y in zip(a, b, strict=True))
                   for a, b in ((self.items, other.items), (self.fence, other.fence), (self.rally, other.rally)))

    def same_as(self, other: Mission) -> bool:
        """Exact equality of everything a file keeps, NaN equal to NaN (for file round trips)."""
        def same_list(a: list[MissionItem], b: list[MissionItem]) -> bool:
            return len(a) == len(b) and all(_identical(x, y) for x, y in zip(a, b, strict=True))

        def same_home(a: PlannedHome | None, b: PlannedHome | None) -> bool:
            if a is None or b is None:
                return a is b
            return all(_same_value(x, y) for x, y in zip(astuple(a), astuple(b), strict=True))

        return (same_home(self.home, other.home) and same_list(self.items, other.items)
                and same_list(self.fence, other.fence) and same_list(self.rally, other.rally)
                and self.plan == other.plan and self.item_info == other.item_info
                and self.home_current == other.home_current)
