"""`QGC WPL 110` waypoint files <-> Mission.

First line `QGC WPL 110`, then one tab-separated row per item:
INDEX CURRENT FRAME COMMAND P1 P2 P3 P4 LAT LON ALT AUTOCONTINUE. Row 0 is home (ArduPilot's convention), so
rows 1..n are the mission items with the same sequence numbers they get on the wire. Rows count in file order:
an INDEX out of order is renumbered (the mission's notes say so), as pymavlink's loader, MAVProxy and QGC do.
As pymavlink and MAVProxy read it: lines starting with `#` are comments, spaces may separate the columns, a file
may hold home alone. A file whose first row is a fence command (5000-5004) or a rally point (5100) is a fence or
rally file, as MAVProxy's `fence save`/`rally save` write them: every row is an item of that list, numbered from 0,
with no home.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from missions.errors import MissionFileError
from missions.model import (
    FENCE_COMMANDS,
    RALLY_COMMANDS,
    Frame,
    MavCmd,
    Mission,
    MissionItem,
    MissionType,
    PlannedHome,
)
from missions.plan import read_text, write_text
from missions.validate import check_numbering

HEADER = "QGC WPL 110"
COLUMNS = ("INDEX", "CURRENT", "FRAME", "COMMAND", "P1", "P2", "P3", "P4", "LAT", "LON", "ALT", "AUTOCONTINUE")
_INT_COLUMNS = frozenset({"INDEX", "CURRENT", "FRAME", "COMMAND", "AUTOCONTINUE"})
_FLAG_COLUMNS = frozenset({"CURRENT", "AUTOCONTINUE"})


#: A number as the tools that write these files spell it: ASCII digits only (Python's float() would also take
#: Arabic-Indic or full-width digits and underscores, which no tool writes), nan and inf in any case.
_NUMBER = re.compile(r"[+-]?(?:(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|nan|inf|infinity)", re.IGNORECASE | re.ASCII)
_FIELD_SEPARATOR = re.compile(r"[ \t]+")  # tabs, or spaces as some writers use; never other Unicode spaces


def _parse_row(fields: list[str], source: str, where: str) -> dict[str, float | int]:
    row: dict[str, float | int] = {}
    for name, text in zip(COLUMNS, fields, strict=True):
        if not _NUMBER.fullmatch(text):
            raise MissionFileError(source, where, f"{name} is {text!r}; expected a number")
        value = float(text)
        if name in _INT_COLUMNS:
            if not value.is_integer():
                raise MissionFileError(source, where, f"{name} is {text!r}; expected a whole number")
            value = int(value)
            if name in _FLAG_COLUMNS and value not in (0, 1):
                raise MissionFileError(source, where, f"{name} is {text!r}; expected 0 or 1")
        row[name] = value
    return row


def loads_wpl(text: str, source: str = "<waypoints>") -> Mission:
    """Parse QGC WPL 110 text; MissionFileError (`source: line N: reason`) for anything malformed."""
    lines = [line.removesuffix("\r") for line in text.split("\n")]  # only a newline ends a line, as in the tools
    first = lines[0].strip() if lines else ""
    if first != HEADER:
        raise MissionFileError(source, "line 1", f"header is {first!r}; expected {HEADER!r}")
    mission = Mission()
    expected_index = 0
    kind = MissionType.MISSION
    renumbered = ""
    for lineno, line in enumerate(lines[1:], 2):
        if not line.strip(" \t") or line.lstrip(" \t").startswith("#"):
            continue  # blank lines and comments carry nothing
        where = f"line {lineno}"
        fields = _FIELD_SEPARATOR.split(line.strip(" \t"))
        if len(fields) != len(COLUMNS):
            raise MissionFileError(source, where, f"has {len(fields)} columns; expected {len(COLUMNS)} "
                                                  f"({' '.join(COLUMNS)}, tab-separated)")
        row = _parse_row(fields, source, where)
        if row["INDEX"] != expected_index and not renumbered:  # as pymavlink, MAVProxy and QGC read it
            renumbered = f"{where} has INDEX {row['INDEX']} where {expected_index} was expected"
        if expected_index == 0:
            kind = (MissionType.FENCE if row["COMMAND"] in FENCE_COMMANDS else
                    MissionType.RALLY if row["COMMAND"] in RALLY_COMMANDS else MissionType.MISSION)
        item = MissionItem(expected_index, row["COMMAND"], row["FRAME"], row["P1"], row["P2"], row["P3"], row["P4"],
                           row["LAT"], row["LON"], row["ALT"], autocontinue=bool(row["AUTOCONTINUE"]),
                           current=bool(row["CURRENT"]), mission_type=kind)
        if kind == MissionType.FENCE:
            mission.fence.append(item)
        elif kind == MissionType.RALLY:
            mission.rally.append(item)
        elif expected_index == 0:
            mission.home_current = item.current
            if row["LAT"] != 0.0 or row["LON"] != 0.0:
                mission.home = PlannedHome(row["LAT"], row["LON"], row["ALT"])
        else:
            mission.items.append(item)
        mission.origins[(kind, expected_index)] = where
        expected_index += 1
    if renumbered:
        mission.notes.append(f"rows renumbered in file order from 0 ({renumbered}), as QGroundControl, MAVProxy "
                             f"and pymavlink read them")
    return mission


def _fmt(x: float) -> str:
    """Shortest text that reads back to the same double (repr), whole numbers without '.0'."""
    x = float(x)
    if math.isfinite(x) and x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(x)  # 'nan' and 'inf' included, as float() reads them


def dumps_wpl(mission: Mission, source: str = "<waypoints>") -> str:
    """The mission as QGC WPL 110 text; a fence or rally list alone as a fence or rally file (rows from 0, no home).
    Refuses a mission with items of more than one list, which one file cannot hold."""
    lists = [items for items in (mission.fence, mission.rally) if items]
    if len(lists) == 1 and not mission.items and mission.home is None:
        body = ["\t".join(_fmt(v) if isinstance(v, float) else str(v) for v in _row(k, item))
                for k, item in enumerate(lists[0])]
        return "\n".join([HEADER, *body]) + "\n"
    if mission.fence or mission.rally:
        raise MissionFileError(source, "", f"QGC WPL 110 holds mission items only; this mission also has "
                                           f"{len(mission.fence)} fence items and {len(mission.rally)} rally points "
                                           f"(save it as .plan to keep them)")
    h = mission.home or PlannedHome(0.0, 0.0, 0.0)
    rows = [[0, int(mission.home_current), int(Frame.GLOBAL), int(MavCmd.NAV_WAYPOINT), 0, 0, 0, 0, h.lat_deg,
             h.lon_deg, h.alt_m, 1]]
    check_numbering(mission, source)
    rows += [_row(k, item) for k, item in enumerate(mission.items, 1)]
    body = ["\t".join(_fmt(v) if isinstance(v, float) else str(v) for v in row) for row in rows]
    return "\n".join([HEADER, *body]) + "\n"


def _row(index: int, item: MissionItem) -> list:
    return [index, int(item.current), int(item.frame), int(item.command), item.p1, item.p2, item.p3, item.p4,
            item.lat_deg, item.lon_deg, item.alt_m, int(bool(item.autocontinue))]


def read_wpl(path: str | Path) -> Mission:
    return loads_wpl(read_text(path), str(path))


def write_wpl(mission: Mission, path: str | Path) -> None:
    write_text(path, dumps_wpl(mission, str(path)))
