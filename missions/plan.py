"""QGroundControl `.plan` files (JSON) <-> Mission.

Format as QGC writes it: fileType "Plan", version 1; mission{version 2, firmwareType, vehicleType, cruiseSpeed,
hoverSpeed, plannedHomePosition [lat, lon, alt AMSL], items}; geoFence{version 2, polygons, circles, breachReturn};
rallyPoints{version 2, points}. Only SimpleItems have a MAVLink meaning. A survey or corridor scan (QGC's
TransectStyleComplexItem) stores the SimpleItems QGC generated for it under `TransectStyleComplexItem.Items`, and QGC
uploads exactly those in their place: so are they read here, in order, numbered on from the items before. A
complex item that stores none (a structure scan, a landing pattern: QGC generates them only when it loads the plan)
is refused by name.

Older files QGC still loads are read as it reads them: items with four params and a `coordinate` [lat, lon, alt]
(params 5-7) or with param1..param4 keys; geoFence and rallyPoints of version 1, which QGC ignores (so does this
reader when they are empty; with content, it refuses rather than drop it); and the pre-.plan `.mission` file
(no fileType, version 2: the mission section at the top level).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

from missions.errors import MissionFileError
from missions.model import (
    PLAN_ALTITUDE_KEYS,
    Frame,
    MavCmd,
    Mission,
    MissionItem,
    MissionType,
    PlanInfo,
    PlanItemInfo,
    PlannedHome,
)
from missions.validate import NO_ALT_COMMANDS, POSITION_COMMANDS, check_numbering

PLAN_VERSION = 1
MISSION_VERSION = 2
GEOFENCE_VERSION = 2
RALLY_VERSION = 2
SHAPE_VERSION = 1  # QGC's version of one fence polygon or circle object
#: Frames QGC uploads fence and rally items with; the .plan itself has no frame for them.
FENCE_SHAPE_FRAME = Frame.GLOBAL
FENCE_RETURN_FRAME = Frame.GLOBAL_RELATIVE_ALT
RALLY_FRAME = Frame.GLOBAL_RELATIVE_ALT
#: QGC's AltitudeMode numbers: 1 relative to home, 2 AMSL, 3 AMSL computed from height above terrain, 4 terrain frame
ALTITUDE_MODE_BY_FRAME = {
    Frame.GLOBAL_RELATIVE_ALT: 1, Frame.GLOBAL_RELATIVE_ALT_INT: 1, Frame.GLOBAL: 2, Frame.GLOBAL_INT: 2,
    Frame.GLOBAL_TERRAIN_ALT: 4, Frame.GLOBAL_TERRAIN_ALT_INT: 4,
}
ALTITUDE_MODE_CALC_ABOVE_TERRAIN = 3


# ---- reading ---------------------------------------------------------------------------------------------------
class _Reader:
    """Typed field access that turns every shape mistake into a MissionFileError naming the place."""

    def __init__(self, source: str):
        self.source = source

    def fail(self, where: str, reason: str) -> MissionFileError:
        return MissionFileError(self.source, where, reason)

    def obj(self, value: Any, where: str, what: str) -> dict:
        if not isinstance(value, dict):
            raise self.fail(where, f"{what} is {_json_type(value)}; expected a JSON object")
        return value

    def field(self, obj: dict, key: str, where: str, kinds: tuple[str, ...], default: Any = ...) -> Any:
        if key not in obj:
            if default is not ...:
                return default
            raise self.fail(where, f'missing field "{key}" (expected {" or ".join(kinds)})')
        value = obj[key]
        if _json_type(value) not in kinds:
            raise self.fail(where, f'field "{key}" is {_json_type(value)}; expected {" or ".join(kinds)}')
        return value

    def number(self, obj: dict, key: str, where: str, default: Any = ...) -> float:
        value = self.field(obj, key, where, ("a number",), default)
        return value if value is default else self.to_float(value, f'field "{key}"', where)

    def to_float(self, value, what: str, where: str) -> float:
        """A JSON number as a double; an integer too large for one is an error naming it, not an OverflowError."""
        try:
            return float(value)
        except OverflowError:
            raise self.fail(where, f"{what} is a number too large for a double; expected at most 1.8e308") from None

    def integer(self, obj: dict, key: str, where: str, default: Any = ...) -> int:
        value = self.field(obj, key, where, ("a number",), default)
        if value is default:
            return value
        number = self.to_float(value, f'field "{key}"', where)
        if not math.isfinite(number) or number != int(number):
            raise self.fail(where, f'field "{key}" is {value}; expected a whole number')
        return int(number)

    def numbers(self, obj: dict, key: str, where: str, sizes: tuple[int, ...], default: Any = ...) -> list[float]:
        """A list of numbers where JSON null stands for NaN (QGC writes NaN params as null)."""
        value = self.field(obj, key, where, ("a list",), default)
        if value is default:
            return value
        expected = " or ".join(str(n) for n in sizes)
        if len(value) not in sizes:
            raise self.fail(where, f'field "{key}" has {len(value)} entries; expected {expected}')
        out = []
        for k, x in enumerate(value):
            if _json_type(x) not in ("a number", "null"):
                raise self.fail(where, f'field "{key}" entry {k} is {_json_type(x)}; expected a number or null')
            out.append(math.nan if x is None else self.to_float(x, f'field "{key}" entry {k}', where))
        return out


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number (QGroundControl writes null for an unset value)")


def _json_type(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, int | float):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "a list"
    return "an object" if isinstance(value, dict) else type(value).__name__


def loads_plan(text: str, source: str = "<plan>") -> Mission:
    """Parse .plan JSON text; MissionFileError (`source: where: reason`) for anything malformed."""
    r = _Reader(source)
    try:
        doc = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as err:
        raise r.fail(f"line {err.lineno} column {err.colno}", f"not valid JSON ({err.msg})") from None
    except ValueError as err:  # NaN/Infinity (not JSON), or an integer of more digits than Python converts
        raise r.fail("top level", f"not valid JSON: {err}") from None
    except RecursionError:
        raise r.fail("top level", "not valid JSON: nested deeper than any plan is") from None
    top = r.obj(doc, "top level", "the file")
    if top.get("fileType", "Mission") == "Mission" and "items" in top and "mission" not in top:
        return _read_mission_file(r, top)
    file_type = r.field(top, "fileType", "top level", ("a string",))
    if file_type != "Plan":
        raise r.fail("top level", f'fileType is "{file_type}"; expected "Plan" (or a QGroundControl .mission)')
    version = r.integer(top, "version", "top level")
    if version != PLAN_VERSION:
        raise r.fail("top level", f"version is {version}; expected {PLAN_VERSION} (QGroundControl plan format)")
    ground_station = r.field(top, "groundStation", "top level", ("a string",), PlanInfo.ground_station)
    m = r.obj(r.field(top, "mission", "top level", ("an object",)), "mission", "mission")
    mission = _read_mission_section(r, m, "mission", ground_station)
    if "geoFence" in top:
        _read_fence(r, r.obj(top["geoFence"], "geoFence", "geoFence"), mission)
    if "rallyPoints" in top:
        _read_rally(r, r.obj(top["rallyPoints"], "rallyPoints", "rallyPoints"), mission)
    return mission


def _read_mission_file(r: _Reader, top: dict) -> Mission:
    """QGC's pre-.plan `.mission` JSON: version 2 is the mission section at the top level; version 1 kept its
    planned home as an object and complex items apart, and QGC converts it only when loading."""
    version = r.integer(top, "version", "top level")
    if version != MISSION_VERSION:
        raise r.fail("top level", f"a QGroundControl .mission file of version {version}; this reader takes version "
                                  f"{MISSION_VERSION}: open it in QGroundControl and save it as a .plan")
    ground_station = r.field(top, "groundStation", "top level", ("a string",), PlanInfo.ground_station)
    return _read_mission_section(r, top, "top level", ground_station)


def _read_mission_section(r: _Reader, m: dict, where: str, ground_station: str) -> Mission:
    mission_version = r.integer(m, "version", where)
    if mission_version != MISSION_VERSION:
        raise r.fail(where, f"version is {mission_version}; expected {MISSION_VERSION}")
    plan = PlanInfo(
        ground_station=ground_station,
        firmware_type=r.integer(m, "firmwareType", where, PlanInfo.firmware_type),
        vehicle_type=r.integer(m, "vehicleType", where, PlanInfo.vehicle_type),
        cruise_speed_mps=r.number(m, "cruiseSpeed", where, PlanInfo.cruise_speed_mps),
        hover_speed_mps=r.number(m, "hoverSpeed", where, PlanInfo.hover_speed_mps),
        global_plan_altitude_mode=r.integer(m, "globalPlanAltitudeMode", where, None),
    )
    raw_items = r.field(m, "items", where, ("a list",))
    # A plan of only a fence or rally points (QGC saves and loads those) has no home to fly from: QGC writes its
    # unknown planned home as nulls, or none at all. With a mission to fly, the home is checked as ever.
    raw_home = m.get("plannedHomePosition")
    no_home = raw_home is None or (isinstance(raw_home, list) and all(x is None for x in raw_home))
    home = None
    if raw_items or not no_home:
        home_lat, home_lon, home_alt = r.numbers(m, "plannedHomePosition", where, (3,))
        if home_lat != 0.0 or home_lon != 0.0:
            home = PlannedHome(home_lat, home_lon, home_alt)
    mission = Mission(home=home, plan=plan)
    mission.origins[(MissionType.MISSION, 0)] = f"{where} plannedHomePosition".removeprefix("top level ")
    _read_items(r, raw_items, mission)
    return mission


def _item_params(r: _Reader, obj: dict, where: str) -> list[float]:
    """Params 1-7 of a SimpleItem as QGC writes it now, or as older QGC did: four params and a `coordinate`
    [lat, lon, alt], or param1..param4 keys (QGC converts both on load)."""
    if "params" not in obj and all(f"param{k}" in obj for k in range(1, 5)):
        params = [r.number(obj, f"param{k}", where) for k in range(1, 5)]
    else:
        params = r.numbers(obj, "params", where, (4, 7) if "coordinate" in obj else (7,))
    if "coordinate" in obj:
        if len(params) != 4:
            raise r.fail(where, f'has "coordinate" and {len(params)} params; expected 4 params with a coordinate')
        params += r.numbers(obj, "coordinate", where, (3,))
    elif len(params) != 7:
        raise r.fail(where, f'field "params" has {len(params)} entries; expected 7 (or 4 with a "coordinate")')
    return params


def _simple_items(r: _Reader, raw_items: list, mission: Mission) -> list[tuple[str, dict]]:
    """(where, SimpleItem object) in the order QGC uploads them: a survey's or corridor scan's stored items in its
    place. QGC's own names: TransectStyleComplexItem::_save writes them under "Items"."""
    found = []
    for k, raw in enumerate(raw_items, 1):
        where = f"item {k}"
        obj = r.obj(raw, where, "the item")
        kind = r.field(obj, "type", where, ("a string",))
        if kind != "ComplexItem":
            if kind not in ("SimpleItem", "missionItem"):  # the second: QGC's first JSON format
                raise r.fail(where, f'type is "{kind}"; expected "SimpleItem" or "ComplexItem"')
            found.append((where, obj))
            continue
        complex_type = obj.get("complexItemType", "unknown")
        where = f'item {k} (ComplexItem "{complex_type}")'
        transect = obj.get("TransectStyleComplexItem")
        stored = transect.get("Items") if isinstance(transect, dict) else None
        if not stored:
            raise r.fail(where, "stores no mission items (QGroundControl generates this kind's items when it "
                                "loads the plan, and uploads those): load the plan in QGroundControl, upload it and "
                                "download it (nac-ground mission download), or replace it with SimpleItems")
        if not isinstance(stored, list):
            raise r.fail(where, f'field "TransectStyleComplexItem.Items" is {_json_type(stored)}; expected a list')
        for j, inner in enumerate(stored, 1):
            inner_where = f"{where} stored item {j}"
            inner_obj = r.obj(inner, inner_where, "the stored item")
            inner_kind = r.field(inner_obj, "type", inner_where, ("a string",), "SimpleItem")
            if inner_kind != "SimpleItem":
                raise r.fail(inner_where, f'type is "{inner_kind}"; expected "SimpleItem"')
            found.append((inner_where, inner_obj))
        mission.notes.append(f'{where}: its {len(stored)} stored items read in its place, as QGroundControl '
                             f'uploads them')
    return found


def _read_items(r: _Reader, raw_items: list, mission: Mission) -> None:
    seq_by_jump_id: dict[int, int] = {}
    where_by_jump_id: dict[int, str] = {}
    for seq, (place, obj) in enumerate(_simple_items(r, raw_items, mission), 1):
        where = place
        if isinstance(obj.get("doJumpId"), int) and not isinstance(obj.get("doJumpId"), bool):
            where = f"{place} (doJumpId {obj['doJumpId']})"
        jump_id = r.integer(obj, "doJumpId", where, seq)
        if jump_id < 1:
            raise r.fail(where, f"doJumpId {jump_id} is not positive; QGC numbers items from 1")
        if jump_id in seq_by_jump_id:
            raise r.fail(where, f"doJumpId {jump_id} is already used by {where_by_jump_id[jump_id]}; "
                                f"expected a unique doJumpId per item")
        seq_by_jump_id[jump_id], where_by_jump_id[jump_id] = seq, place
        command = r.integer(obj, "command", where)
        frame = r.integer(obj, "frame", where)
        params = _item_params(r, obj, where)
        auto = r.field(obj, "autoContinue", where, ("a boolean", "a number"))
        mission.items.append(MissionItem(seq, command, frame, *params, autocontinue=bool(auto),
                                         mission_type=MissionType.MISSION))
        mission.item_info[seq] = PlanItemInfo(jump_id, {k: obj[k] for k in PLAN_ALTITUDE_KEYS if k in obj})
        mission.origins[(MissionType.MISSION, seq)] = where
    # DO_JUMP names its target by doJumpId in a .plan but by sequence number on the wire.
    for k, item in enumerate(mission.items):
        if item.command == MavCmd.DO_JUMP and math.isfinite(item.p1) and item.p1 == int(item.p1):
            target = seq_by_jump_id.get(int(item.p1))
            if target is None:
                raise r.fail(mission.where(MissionType.MISSION, item.seq),
                             f"DO_JUMP target doJumpId {int(item.p1)} is not the doJumpId of any item "
                             f"(this plan has {', '.join(map(str, seq_by_jump_id)) or 'none'})")
            mission.items[k] = replace(item, p1=float(target))


def _ignored_old_version(r: _Reader, section: dict, name: str, content_keys: tuple[str, ...]) -> bool:
    """QGC ignores geoFence and rallyPoints of version 1: so does this reader, when there is nothing to lose."""
    if section.get("version") != 1:
        return False
    held = [key for key in content_keys if section.get(key)]
    if held:
        raise r.fail(name, f"version 1 with {', '.join(held)}: QGroundControl ignores version 1 {name} on load, so it "
                           f"would be lost; draw it again in QGroundControl 4 and save the plan (version 2)")
    return True


def _read_fence(r: _Reader, fence: dict, mission: Mission) -> None:
    if _ignored_old_version(r, fence, "geoFence", ("polygon", "polygons", "circles", "breachReturn")):
        return
    version = r.integer(fence, "version", "geoFence")
    if version != GEOFENCE_VERSION:
        raise r.fail("geoFence", f"version is {version}; expected {GEOFENCE_VERSION} (polygons and circles)")

    def add(where: str, command: int, frame: int, p1: float, lat: float, lon: float, alt: float = 0.0) -> None:
        seq = len(mission.fence)
        mission.fence.append(MissionItem(seq, command, frame, p1, lat_deg=lat, lon_deg=lon, alt_m=alt,
                                         mission_type=MissionType.FENCE))
        mission.origins[(MissionType.FENCE, seq)] = where

    for j, raw in enumerate(r.field(fence, "polygons", "geoFence", ("a list",)), 1):
        where = f"geoFence polygon {j}"
        poly = r.obj(raw, where, "the polygon")
        inclusion = r.field(poly, "inclusion", where, ("a boolean",))
        vertices = r.field(poly, "polygon", where, ("a list",))
        command = MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION if inclusion else MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION
        for v, vertex in enumerate(vertices, 1):
            lat, lon = r.numbers({"vertex": vertex}, "vertex", f"{where} vertex {v}", (2,))
            add(f"{where} vertex {v}", command, FENCE_SHAPE_FRAME, float(len(vertices)), lat, lon)
        if len(vertices) < 3:
            raise r.fail(where, f"has {len(vertices)} vertices; expected at least 3")
    for j, raw in enumerate(r.field(fence, "circles", "geoFence", ("a list",)), 1):
        where = f"geoFence circle {j}"
        obj = r.obj(raw, where, "the circle")
        inclusion = r.field(obj, "inclusion", where, ("a boolean",))
        circle = r.obj(r.field(obj, "circle", where, ("an object",)), where, "circle")
        lat, lon = r.numbers(circle, "center", where, (2,))
        radius_m = r.number(circle, "radius", where)
        command = MavCmd.NAV_FENCE_CIRCLE_INCLUSION if inclusion else MavCmd.NAV_FENCE_CIRCLE_EXCLUSION
        add(where, command, FENCE_SHAPE_FRAME, radius_m, lat, lon)
    if "breachReturn" in fence:
        lat, lon, alt = r.numbers(fence, "breachReturn", "geoFence", (3,))
        add("geoFence breachReturn", MavCmd.NAV_FENCE_RETURN_POINT, FENCE_RETURN_FRAME, 0.0, lat, lon, alt)


def _read_rally(r: _Reader, rally: dict, mission: Mission) -> None:
    if _ignored_old_version(r, rally, "rallyPoints", ("points",)):
        return
    version = r.integer(rally, "version", "rallyPoints")
    if version != RALLY_VERSION:
        raise r.fail("rallyPoints", f"version is {version}; expected {RALLY_VERSION}")
    for j, raw in enumerate(r.field(rally, "points", "rallyPoints", ("a list",)), 1):
        where = f"rallyPoints point {j}"
        lat, lon, alt = r.numbers({"point": raw}, "point", where, (3,))
        seq = len(mission.rally)
        mission.rally.append(MissionItem(seq, MavCmd.NAV_RALLY_POINT, RALLY_FRAME, lat_deg=lat, lon_deg=lon,
                                         alt_m=alt, mission_type=MissionType.RALLY))
        mission.origins[(MissionType.RALLY, seq)] = where


# ---- writing ---------------------------------------------------------------------------------------------------
def _num(x: float, source: str, where: str) -> int | float | None:
    """JSON number as QGC writes it: whole numbers without '.0', NaN as null."""
    x = float(x)
    if math.isnan(x):
        return None
    if math.isinf(x):
        raise MissionFileError(source, where, f"value {x} cannot be written to JSON; expected a finite number")
    return int(x) if x.is_integer() and abs(x) < 2 ** 53 else x


def _altitude_keys(item: MissionItem, info: PlanItemInfo | None, source: str, where: str) -> dict[str, Any]:
    """QGC's altitude keys: as read while they still describe the item, else derived from its frame and alt."""
    alt = _num(item.alt_m, source, where)
    if info is not None:
        keys = info.altitude_keys
        if not keys:
            return {}  # the file had none (older QGC, or a command without altitude): keep it that way
        mode = keys.get("AltitudeMode")
        if mode == ALTITUDE_MODE_CALC_ABOVE_TERRAIN or (
                mode == ALTITUDE_MODE_BY_FRAME.get(item.frame) and keys.get("Altitude") == alt):
            return dict(keys)
    mode = ALTITUDE_MODE_BY_FRAME.get(item.frame)
    if item.command not in POSITION_COMMANDS or item.command in NO_ALT_COMMANDS or mode is None:
        return {}
    return {"AMSLAltAboveTerrain": None, "Altitude": alt, "AltitudeMode": mode}


def dumps_plan(mission: Mission, source: str = "<plan>") -> str:
    """The mission as .plan JSON text, keys sorted and 4-space indented as QGC writes it."""
    check_numbering(mission, source)
    seqs = [item.seq for item in mission.items]
    jump_ids = [mission.item_info[s].do_jump_id if s in mission.item_info else s for s in seqs]
    if len(set(jump_ids)) != len(jump_ids) or min(jump_ids, default=1) < 1:
        jump_ids = list(range(1, len(seqs) + 1))  # kept ids collide with new items: renumber, jumps follow
    jump_id_by_seq = dict(zip(seqs, jump_ids, strict=True))
    items = []
    for item, jump_id in zip(mission.items, jump_ids, strict=True):
        where = mission.where(MissionType.MISSION, item.seq)
        p1 = item.p1
        if item.command == MavCmd.DO_JUMP and math.isfinite(p1) and int(p1) in jump_id_by_seq:
            p1 = float(jump_id_by_seq[int(p1)])
        params = [_num(x, source, where) for x in (p1, item.p2, item.p3, item.p4, item.lat_deg, item.lon_deg,
                                                    item.alt_m)]
        entry = {"autoContinue": bool(item.autocontinue), "command": int(item.command), "doJumpId": jump_id,
                 "frame": int(item.frame), "params": params, "type": "SimpleItem"}
        entry.update(_altitude_keys(item, mission.item_info.get(item.seq), source, where))
        items.append(entry)
    home = mission.home or PlannedHome(0.0, 0.0, 0.0)
    plan = mission.plan
    mission_obj = {
        "cruiseSpeed": _num(plan.cruise_speed_mps, source, "mission"),
        "firmwareType": plan.firmware_type,
        "hoverSpeed": _num(plan.hover_speed_mps, source, "mission"),
        "items": items,
        "plannedHomePosition": [_num(x, source, "planned home") for x in (home.lat_deg, home.lon_deg, home.alt_m)],
        "vehicleType": plan.vehicle_type,
        "version": MISSION_VERSION,
    }
    if plan.global_plan_altitude_mode is not None:
        mission_obj["globalPlanAltitudeMode"] = plan.global_plan_altitude_mode
    doc = {
        "fileType": "Plan",
        "geoFence": _fence_json(mission, source),
        "groundStation": plan.ground_station,
        "mission": mission_obj,
        "rallyPoints": {"points": [[_num(x, source, mission.where(MissionType.RALLY, p.seq))
                                    for x in (p.lat_deg, p.lon_deg, p.alt_m)] for p in mission.rally],
                        "version": RALLY_VERSION},
        "version": PLAN_VERSION,
    }
    return json.dumps(doc, indent=4, sort_keys=True, allow_nan=False) + "\n"


def _fence_json(mission: Mission, source: str) -> dict:
    polygons: list[dict] = []
    circles: list[dict] = []
    out: dict[str, Any] = {"circles": circles, "polygons": polygons, "version": GEOFENCE_VERSION}
    fence = mission.fence
    k = 0
    while k < len(fence):
        item = fence[k]
        where = mission.where(MissionType.FENCE, item.seq)

        def point(it: MissionItem, with_alt: bool = False, where: str = where) -> list:
            coords = (it.lat_deg, it.lon_deg, it.alt_m) if with_alt else (it.lat_deg, it.lon_deg)
            return [_num(x, source, where) for x in coords]

        if item.command in (MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION, MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION):
            count = int(item.p1) if math.isfinite(item.p1) and item.p1 >= 1 else 0
            run = fence[k:k + count]
            if count < 1 or len(run) < count or any(v.command != item.command for v in run):
                raise MissionFileError(source, where, f"polygon vertex run (param1 = {item.p1}) does not match the "
                                                      f"items that follow; cannot write it as a .plan polygon")
            polygons.append({"inclusion": item.command == MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION,
                             "polygon": [point(v) for v in run], "version": SHAPE_VERSION})
            k += count
            continue
        if item.command in (MavCmd.NAV_FENCE_CIRCLE_INCLUSION, MavCmd.NAV_FENCE_CIRCLE_EXCLUSION):
            circles.append({"circle": {"center": point(item), "radius": _num(item.p1, source, where)},
                            "inclusion": item.command == MavCmd.NAV_FENCE_CIRCLE_INCLUSION,
                            "version": SHAPE_VERSION})
        elif item.command == MavCmd.NAV_FENCE_RETURN_POINT and "breachReturn" not in out:
            out["breachReturn"] = point(item, with_alt=True)
        else:
            raise MissionFileError(source, where, f"fence command {item.command} has no place in a .plan geoFence "
                                                  f"(polygons, circles and one breachReturn)")
        k += 1
    return out


# ---- files -----------------------------------------------------------------------------------------------------
MAX_MISSION_BYTES = 8 * 1024 * 1024  # a mission of 10,000 items is about 4 MB of .plan


def read_text(path: str | Path) -> str:
    """A mission file's text: only a regular file of at most MAX_MISSION_BYTES, checked with os.stat before it is
    opened and opened without blocking, so a FIFO, a device (/dev/zero) or a huge file is refused, not read (the
    mission library's own copy of nac_onboard.inputs.read_bounded: missions imports nothing of NAC's)."""
    import os
    import stat

    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise MissionFileError(str(path), "", "not a regular file (a FIFO, device or directory); expected a "
                                                  "mission file")
        if st.st_size > MAX_MISSION_BYTES:
            raise MissionFileError(str(path), "", f"{st.st_size} bytes; a mission file may have at most "
                                                  f"{MAX_MISSION_BYTES}")
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise MissionFileError(str(path), "", "not a regular file; expected a mission file")
            data = f.read(MAX_MISSION_BYTES + 1)
        if len(data) > MAX_MISSION_BYTES:
            raise MissionFileError(str(path), "", f"grew past {MAX_MISSION_BYTES} bytes while read")
        return data.decode("utf-8-sig")  # tolerate a BOM from Windows editors
    except (OSError, UnicodeDecodeError) as err:
        reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
        raise MissionFileError(str(path), "", f"cannot read the file ({reason})") from None


def write_text(path: str | Path, text: str) -> None:
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as err:
        raise MissionFileError(str(path), "", f"cannot write the file ({err.strerror or err})") from None


def read_plan(path: str | Path) -> Mission:
    return loads_plan(read_text(path), str(path))


def write_plan(mission: Mission, path: str | Path) -> None:
    write_text(path, dumps_plan(mission, str(path)))
