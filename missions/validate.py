"""Checks a mission before it flies: positions on the globe, altitudes a multirotor can hold, frames and
commands the vehicle understands, jumps that land on an item. Raises MissionFileError naming the item."""

from __future__ import annotations

import math

from missions.dialect import MODEL_CATALOGUE, CommandCatalogue, DialectCommand
from missions.errors import MissionFileError
from missions.firmware import Firmware
from missions.model import (
    FENCE_COMMANDS,
    RALLY_COMMANDS,
    Frame,
    MavCmd,
    Mission,
    MissionItem,
    MissionType,
    command_name,
    frame_name,
)

AMSL_ALT_LIMITS_M = (-500.0, 10000.0)  # Dead Sea shore to well above any multirotor's ceiling
RELATIVE_ALT_LIMITS_M = (-100.0, 10000.0)  # a valley below home, not a hole in the ground
ALT_LIMITS_M = {
    Frame.GLOBAL: AMSL_ALT_LIMITS_M, Frame.GLOBAL_INT: AMSL_ALT_LIMITS_M,
    Frame.GLOBAL_RELATIVE_ALT: RELATIVE_ALT_LIMITS_M, Frame.GLOBAL_RELATIVE_ALT_INT: RELATIVE_ALT_LIMITS_M,
    Frame.GLOBAL_TERRAIN_ALT: RELATIVE_ALT_LIMITS_M, Frame.GLOBAL_TERRAIN_ALT_INT: RELATIVE_ALT_LIMITS_M,
}
#: Frames the SITL flies for items with a position; commands without one may also say MISSION (QGC writes 2).
POSITION_FRAMES = frozenset(ALT_LIMITS_M)
NON_POSITION_FRAMES = POSITION_FRAMES | {Frame.MISSION}
#: Commands whose x/y/z are latitude/longitude/altitude.
POSITION_COMMANDS = frozenset({16, 17, 18, 19, 21, 22, 31, 82, 84, 85, 94}) | FENCE_COMMANDS | RALLY_COMMANDS
#: Fence shapes have no altitude: the fence's altitude limits are parameters, not items.
NO_ALT_COMMANDS = frozenset({5001, 5002, 5003, 5004})
#: ArduPilot reads lat = lon = 0 as "where the vehicle is" for its navigation commands (take off here, land here,
#: loiter here...); only a fence vertex or a rally point at 0, 0 is taken for a mistake.
ZERO_IS_HERE_COMMANDS = frozenset({16, 17, 18, 19, 20, 21, 22, 31, 36, 82, 84, 85, 93, 94})
JUMP_TAG, DO_JUMP_TAG = 600, 601
POLYGON_COMMANDS = frozenset({5001, 5002})
CIRCLE_COMMANDS = frozenset({5003, 5004})


#: MISSION_ITEM_INT on the wire: params 1-4 and z are float32, x and y int32 in 1e-7 degrees, the count uint16.
FLOAT32_MAX = 3.4028234663852886e38
INT32_DEGREES_MAX = (2 ** 31 - 1) / 1e7  # 214.7483647
MAX_ITEMS = 65535


def _wire_problem(item: MissionItem) -> str | None:
    """What of the item MAVLink cannot carry: NaN is allowed where MAVLink means "unset" (params, and x/y/z of a
    command without a position, which go out as 0)."""
    for label, value in (("param1", item.p1), ("param2", item.p2), ("param3", item.p3), ("param4", item.p4),
                         ("altitude (param7)", item.alt_m)):
        if math.isinf(value) or (math.isfinite(value) and abs(value) > FLOAT32_MAX):
            return f"{label} is {_fmt(value)}; MAVLink carries it as a 32-bit float: expected |value| <= 3.4e38"
    for label, value in (("latitude (param5)", item.lat_deg), ("longitude (param6)", item.lon_deg)):
        if math.isinf(value) or (math.isfinite(value) and abs(value) > INT32_DEGREES_MAX):
            return (f"{label} is {_fmt(value)}; MAVLink carries it as a 32-bit integer of 1e-7 degrees: "
                    f"expected |value| <= {INT32_DEGREES_MAX}")
    if not 0 <= item.frame <= 255:
        return f"frame {item.frame} does not fit MAVLink's 8-bit frame field"
    return None


def _fmt(x: float) -> str:
    x = float(x)
    return "NaN" if math.isnan(x) else f"{x:g}" if abs(x) >= 1e6 else str(x)


def validate(mission: Mission, source: str = "<mission>", flight: bool = True, *,
             catalogue: CommandCatalogue = MODEL_CATALOGUE, firmware: Firmware | None = None) -> None:
    """Raise MissionFileError (`source: item ...: reason`) at the first problem; return None when fit to fly.
    With flight=False only what any file must hold is checked (numbering, values MAVLink can carry), as a
    converter needs: a home-only file, or frames and commands this SITL does not fly, still convert.
    `catalogue` is the commands a mission may hold (missions.dialect): NAC's commands pass the MAVLink dialect's,
    nac_onboard.mavlink.dialect.mission_catalogue(); the default knows only the commands missions.model names.
    `firmware` (missions.firmware): also refuse, naming the item, what that firmware would refuse at upload."""
    def fail(mission_type: int, seq: int, reason: str) -> None:
        raise MissionFileError(source, mission.where(mission_type, seq), reason)

    if mission.home is not None:
        _check_home(mission, fail)
    if flight and not (mission.items or mission.fence or mission.rally):
        raise MissionFileError(source, "mission", "is empty (no mission items); expected at least one "
                               "(a flyable mission starts with NAV_TAKEOFF and ends with NAV_LAND or RTL)")
    for name, items, extra in (("mission", mission.items, 1), ("fence", mission.fence, 0), ("rally", mission.rally, 0)):
        if len(items) + extra > MAX_ITEMS:
            raise MissionFileError(source, name, f"has {len(items)} items; MAVLink counts items in 16 bits: at most "
                                                 f"{MAX_ITEMS - extra}")
    for mission_type, items, first in ((MissionType.MISSION, mission.items, 1), (MissionType.FENCE, mission.fence, 0),
                                       (MissionType.RALLY, mission.rally, 0)):
        for k, item in enumerate(items, first):
            if item.seq != k:
                fail(mission_type, item.seq, f"has sequence number {item.seq} where {k} was expected "
                                             f"(numbers run {first}..{first + len(items) - 1} without gaps or repeats)")
            if item.mission_type != mission_type:
                fail(mission_type, k, f"has mission_type {item.mission_type}, expected {int(mission_type)} "
                                      f"({MissionType(mission_type).name})")
            reason = _wire_problem(item)
            if flight and not reason:
                reason = (_altitude_left_to_qgc(mission, item)
                          or _item_problem(item, mission_type, len(mission.items), catalogue)
                          or _refused_by(firmware, item, mission_type, catalogue))
            if reason:
                fail(mission_type, k, reason)
    if flight:
        _check_fence_shapes(mission, fail)
        _check_jump_tags(mission, fail)


def check_numbering(mission: Mission, source: str = "<mission>") -> None:
    """Writers need items numbered 1..n: DO_JUMP targets and .plan doJumpIds are looked up by seq."""
    for k, item in enumerate(mission.items, 1):
        if item.seq != k:
            raise MissionFileError(source, mission.where(MissionType.MISSION, item.seq),
                                   f"has sequence number {item.seq} where {k} was expected (items are numbered 1..n)")


def _check_home(mission: Mission, fail) -> None:
    h = mission.home
    if math.isnan(h.lat_deg) or math.isnan(h.lon_deg) or math.isnan(h.alt_m):
        fail(MissionType.MISSION, 0, "planned home has a NaN/null coordinate; expected latitude, longitude, "
                                     "altitude AMSL")
    if not -90.0 <= h.lat_deg <= 90.0:
        fail(MissionType.MISSION, 0, f"home latitude {_fmt(h.lat_deg)} is outside -90..90")
    if not -180.0 <= h.lon_deg <= 180.0:
        fail(MissionType.MISSION, 0, f"home longitude {_fmt(h.lon_deg)} is outside -180..180")
    lo, hi = AMSL_ALT_LIMITS_M
    if not lo <= h.alt_m <= hi:
        fail(MissionType.MISSION, 0, f"home altitude {_fmt(h.alt_m)} m AMSL is outside {lo:g}..{hi:g} m")


def _refused_by(firmware: Firmware | None, item: MissionItem, mission_type: int,
                catalogue: CommandCatalogue) -> str | None:
    refusal = firmware.refusal(item, mission_type) if firmware is not None else None
    if refusal is None:
        return None
    why = {"MAV_MISSION_UNSUPPORTED": "a command it does not take",
           "MAV_MISSION_UNSUPPORTED_FRAME": f"frame {item.frame} is not one it takes"}.get(refusal,
                                                                                          "a value out of range")
    return (f"{catalogue.name(item.command)} ({item.command}) would be refused at upload by {firmware.name}: "
            f"{refusal}, {why}")


def _item_problem(item: MissionItem, mission_type: int, n_items: int, catalogue: CommandCatalogue) -> str | None:
    cmd = item.command
    if not catalogue.known(cmd):
        return (f"unknown command {cmd}: neither MAVLink's common nor its ardupilotmega dialect defines it "
                f"(e.g. 16 NAV_WAYPOINT, 22 NAV_TAKEOFF, 21 NAV_LAND, 178 DO_CHANGE_SPEED)")
    name = catalogue.name(cmd)
    if mission_type == MissionType.MISSION and cmd in FENCE_COMMANDS | RALLY_COMMANDS:
        return f"{name} ({cmd}) is a fence/rally command; it belongs in the geofence or rally points, not the mission"
    if mission_type == MissionType.FENCE and cmd not in FENCE_COMMANDS:
        return f"{name} ({cmd}) in the fence; expected a fence command (5000-5004)"
    if mission_type == MissionType.RALLY and cmd not in RALLY_COMMANDS:
        return f"{name} ({cmd}) in the rally points; expected NAV_RALLY_POINT (5100)"
    entry = catalogue.entry(cmd)
    has_position = cmd in POSITION_COMMANDS or _navigates_to_location(cmd, entry)
    frames = POSITION_FRAMES if has_position else NON_POSITION_FRAMES
    if item.frame not in frames:
        allowed = ", ".join(f"{int(f)} {f.name}" for f in sorted(frames))
        return (f"{name} has frame {item.frame} ({frame_name(item.frame)}), which is not flown here; "
                f"expected one of {allowed}")
    if has_position:
        problem = _position_problem(item, name)
        if problem:
            return problem
    elif entry is not None and entry.has_location:
        problem = _location_range_problem(item)  # a DO_ command's optional place (0, 0 or NaN: "here" or unset)
        if problem:
            return problem
    if cmd == MavCmd.DO_JUMP:
        return _jump_problem(item, n_items)
    if cmd == MavCmd.DO_CHANGE_SPEED and not math.isfinite(item.p2):
        return f"DO_CHANGE_SPEED speed (param2) is {_fmt(item.p2)}; expected a number of m/s (-1 = no change)"
    return None


def _position_problem(item: MissionItem, name: str) -> str | None:
    lat, lon = item.lat_deg, item.lon_deg
    for label, value in (("latitude", lat), ("longitude", lon)):
        if math.isnan(value):
            return f"{label} is NaN/null; {name} needs a number (0, 0 means 'here' for take-off/land/waypoint)"
    if not -90.0 <= lat <= 90.0:
        return f"latitude {_fmt(lat)} is outside -90..90"
    if not -180.0 <= lon <= 180.0:
        return f"longitude {_fmt(lon)} is outside -180..180"
    if lat == 0.0 and lon == 0.0 and item.command not in ZERO_IS_HERE_COMMANDS:
        return f"{name} at latitude 0, longitude 0; expected the point's real coordinates"
    if item.command in NO_ALT_COMMANDS:
        return None
    if math.isnan(item.alt_m):
        return f"altitude is NaN/null; {name} needs a number of metres"
    lo, hi = ALT_LIMITS_M[Frame(item.frame)]
    if not lo <= item.alt_m <= hi:
        reference = "AMSL" if lo == AMSL_ALT_LIMITS_M[0] else "above home/terrain"
        return (f"altitude {_fmt(item.alt_m)} m is outside {lo:g}..{hi:g} m "
                f"({reference}, frame {item.frame} {frame_name(item.frame)})")
    return None


def _altitude_left_to_qgc(mission: Mission, item: MissionItem) -> str | None:
    """QGC's altitude mode 3 ("calculated above terrain") leaves the altitude null in the file: QGC computes the
    AMSL altitude from its terrain data when it uploads."""
    info = mission.item_info.get(item.seq) if item.mission_type == MissionType.MISSION else None
    if info is None or info.altitude_keys.get("AltitudeMode") != 3 or not math.isnan(item.alt_m):
        return None
    height = info.altitude_keys.get("Altitude")
    return (f"altitude is null: QGroundControl's altitude mode 3 (calculated above terrain, {height} m) computes "
            f"it from terrain data when it uploads. Upload the plan from QGroundControl and download it "
            f"(nac-ground mission download), or set the item to a relative or AMSL altitude in QGroundControl")


def _navigates_to_location(command: int, entry: DialectCommand | None) -> bool:
    """A NAV_ command the dialect gives a position: its x/y/z get the same checks as a waypoint's."""
    return entry is not None and entry.has_location and entry.name.startswith("NAV_") and command < 5000


def _location_range_problem(item: MissionItem) -> str | None:
    for label, value, limit in (("latitude", item.lat_deg, 90.0), ("longitude", item.lon_deg, 180.0)):
        if math.isfinite(value) and not -limit <= value <= limit:
            return f"{label} {_fmt(value)} is outside -{limit:g}..{limit:g}"
    return None


def _check_jump_tags(mission: Mission, fail) -> None:
    """DO_JUMP_TAG jumps to the JUMP_TAG item with its tag number (param1): that item must exist, once."""
    tags: dict[int, int] = {}
    for item in mission.items:
        if item.command == JUMP_TAG:
            tag = item.p1
            if not math.isfinite(tag) or tag != int(tag) or tag < 0:
                fail(MissionType.MISSION, item.seq, f"JUMP_TAG tag (param1) is {_fmt(tag)}; expected a whole number "
                                                    f">= 0")
            if int(tag) in tags:
                fail(MissionType.MISSION, item.seq, f"JUMP_TAG {int(tag)} is also item {tags[int(tag)]}; expected "
                                                    f"each tag once")
            tags[int(tag)] = item.seq
    for item in mission.items:
        if item.command == DO_JUMP_TAG:
            tag = item.p1
            if not math.isfinite(tag) or tag != int(tag) or int(tag) not in tags:
                known = ", ".join(str(t) for t in sorted(tags)) or "none"
                fail(MissionType.MISSION, item.seq, f"DO_JUMP_TAG target tag (param1) {_fmt(tag)} has no JUMP_TAG "
                                                    f"item; tags in this mission: {known}")


def _jump_problem(item: MissionItem, n_items: int) -> str | None:
    target, repeat = item.p1, item.p2
    if not math.isfinite(target) or target != int(target):
        return f"DO_JUMP target (param1) is {_fmt(target)}; expected the number of an existing item"
    if not 1 <= target <= n_items:
        return f"DO_JUMP target item {int(target)} does not exist; expected an item number 1..{n_items}"
    if not math.isfinite(repeat) or repeat != int(repeat) or repeat < -1:
        return f"DO_JUMP repeat count (param2) is {_fmt(repeat)}; expected a whole number >= -1 (-1 = forever)"
    return None


def _check_fence_shapes(mission: Mission, fail) -> None:
    """Polygon vertices come in runs of param1 items of one command, as the fence protocol sends them."""
    fence = mission.fence
    k = 0
    while k < len(fence):
        item = fence[k]
        if item.command in CIRCLE_COMMANDS and not (math.isfinite(item.p1) and item.p1 > 0):
            fail(MissionType.FENCE, k, f"fence circle radius (param1) is {_fmt(item.p1)}; expected metres > 0")
        if item.command not in POLYGON_COMMANDS:
            k += 1
            continue
        count = item.p1
        if not math.isfinite(count) or count != int(count) or count < 3:
            fail(MissionType.FENCE, k, f"polygon vertex count (param1) is {_fmt(count)}; expected a whole number >= 3")
        count = int(count)
        run = fence[k:k + count]
        for vertex in run:
            if vertex.command != item.command or vertex.p1 != count:
                fail(MissionType.FENCE, vertex.seq, f"expected vertex {vertex.seq - k + 1} of {count} of the polygon "
                                                    f"starting at fence item {k} ({command_name(item.command)}, "
                                                    f"param1 {count})")
        if len(run) < count:
            fail(MissionType.FENCE, k, f"polygon announces {count} vertices but the fence ends after {len(run)}")
        k += count
