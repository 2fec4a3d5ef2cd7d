"""MAVProxy's older rally and fence files -> Mission (read only: NAC writes them as QGC WPL 110).

Before the mission protocol carried fences and rally points, MAVProxy saved them in formats of their own, and its
`rally load` / `fence load` (pymavlink's mavwp loaders) still read them:
- rally: one `RALLY lat lon alt break_alt land_dir flags` line per point (alt and break_alt in metres above home,
  land_dir in degrees); each becomes a NAV_RALLY_POINT relative to home, as mavwp's MissionItemProtocol_Rally makes
  it (break_alt, land_dir and flags have no place in the mission protocol's rally point).
- fence: one `lat lon` line per FENCE_POINT: the return point first, then the polygon's vertices, the last
  repeating the first to close it (at least 5 lines); the return point becomes NAV_FENCE_RETURN_POINT and each
  vertex an inclusion vertex of one polygon, as mavwp's MissionItemProtocol_Fence converts it.
Lines starting with `#` and blank lines are skipped, as those loaders do.
"""

from __future__ import annotations

import re

from missions.errors import MissionFileError
from missions.model import Frame, MavCmd, Mission, MissionItem, MissionType

#: mavwp's test for a legacy fence file: its first line is two numbers
_FENCE_LINE = re.compile(r"[-+]?[0-9.]+\s+[-+]?[0-9.]+\s*$")
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?", re.ASCII)
MIN_FENCE_POINTS = 5  # return point, three vertices, the closing point


def is_legacy(text: str) -> bool:
    first = _first_line(text)
    return first.upper().startswith("RALLY ") or bool(_FENCE_LINE.match(first))


def _first_line(text: str) -> str:
    for line in text.split("\n"):
        line = line.strip()
        if line and not line.startswith("#"):
            return line
    return ""


def _rows(text: str, source: str, columns: int, what: str):
    """(where, fields) per line that carries a point, each field a checked number (the first of a rally line is
    the word RALLY)."""
    for lineno, line in enumerate(text.split("\n"), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        where = f"line {lineno}"
        fields = line.split()
        if len(fields) != columns:
            raise MissionFileError(source, where, f"has {len(fields)} fields; expected {columns} ({what})")
        numbers = fields[1:] if columns == 7 else fields
        for k, text_value in enumerate(numbers):
            if not _NUMBER.fullmatch(text_value):
                raise MissionFileError(source, where, f"field {k + 1 + (columns == 7)} is {text_value!r}; "
                                                      f"expected a number ({what})")
        yield where, fields


def loads_legacy(text: str, source: str = "<legacy>") -> Mission:
    """A MAVProxy rally or fence file (is_legacy(text) said which); MissionFileError names the line."""
    mission = Mission()
    if _first_line(text).upper().startswith("RALLY "):
        for seq, (where, fields) in enumerate(_rows(text, source, 7, "RALLY lat lon alt break_alt land_dir flags")):
            if fields[0].upper() != "RALLY":
                raise MissionFileError(source, where, f"starts with {fields[0]!r}; expected RALLY")
            lat, lon, alt = (float(x) for x in fields[1:4])
            mission.rally.append(MissionItem(seq, MavCmd.NAV_RALLY_POINT, Frame.GLOBAL_RELATIVE_ALT, lat_deg=lat,
                                             lon_deg=lon, alt_m=alt, mission_type=MissionType.RALLY))
            mission.origins[(MissionType.RALLY, seq)] = where
        mission.notes.append(f"a MAVProxy rally file: {len(mission.rally)} rally points (break_alt, land_dir and "
                             f"flags have no place in the mission protocol's rally point)")
        return mission
    points = list(_rows(text, source, 2, "lat lon: the return point, then the polygon closed on its first vertex"))
    if len(points) < MIN_FENCE_POINTS:
        raise MissionFileError(source, points[-1][0] if points else "line 1",
                               f"a MAVProxy fence file of {len(points)} points; expected at least {MIN_FENCE_POINTS} "
                               f"(the return point, three vertices and the first vertex again to close)")
    vertices = points[1:-1]
    for seq, (where, (lat, lon)) in enumerate(points[:-1]):
        command = MavCmd.NAV_FENCE_RETURN_POINT if seq == 0 else MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION
        mission.fence.append(MissionItem(seq, command, Frame.GLOBAL, p1=0.0 if seq == 0 else float(len(vertices)),
                                         lat_deg=float(lat), lon_deg=float(lon), autocontinue=False,
                                         mission_type=MissionType.FENCE))
        mission.origins[(MissionType.FENCE, seq)] = where
    mission.notes.append(f"a MAVProxy fence file: the return point and a polygon of {len(vertices)} vertices "
                         f"(its closing point, {points[-1][0]}, dropped)")
    return mission
