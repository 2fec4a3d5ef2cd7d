"""Mission files by path: the format is chosen by content when reading and by extension when writing."""

from __future__ import annotations

from pathlib import Path

from missions.dialect import MODEL_CATALOGUE, CommandCatalogue
from missions.errors import MissionFileError
from missions.firmware import Firmware
from missions.legacy import is_legacy, loads_legacy
from missions.model import Mission
from missions.plan import loads_plan, read_text, write_plan
from missions.validate import validate
from missions.wpl import HEADER, loads_wpl, write_wpl

PLAN_SUFFIXES = frozenset({".plan"})
WPL_SUFFIXES = frozenset({".waypoints", ".txt"})


def loads_mission(text: str, source: str = "<mission>") -> Mission:
    """Parse .plan, QGC WPL or MAVProxy's older rally or fence text, whichever it is (JSON starts with '{'),
    without validating."""
    start = text.lstrip()
    if start.startswith("{"):
        return loads_plan(text, source)
    if start.startswith("QGC WPL"):
        return loads_wpl(text, source)
    if is_legacy(text):
        return loads_legacy(text, source)
    first = start.splitlines()[0][:40] if start else ""
    raise MissionFileError(source, "line 1", f"starts with {first!r}; expected a QGroundControl .plan "
                                             f"(JSON object), a {HEADER!r} waypoint file, or a MAVProxy rally "
                                             f"(RALLY lines) or fence (lat lon lines) file")


def load_mission(path: str | Path, flight: bool = True, *, catalogue: CommandCatalogue = MODEL_CATALOGUE,
                 firmware: Firmware | None = None) -> Mission:
    """Read and validate a mission file (for flight, or only as a file: validate's `flight`, `catalogue`, the
    commands it may hold, and `firmware`, whose upload refusals it names); MissionFileError names the file, the item
    or line, and the problem."""
    mission = loads_mission(read_text(path), str(path))
    validate(mission, str(path), flight, catalogue=catalogue, firmware=firmware)
    return mission


def save_mission(mission: Mission, path: str | Path) -> None:
    """Write .plan for `.plan`, QGC WPL 110 for `.waypoints`/`.txt` (what QGC and Mission Planner expect)."""
    suffix = Path(path).suffix.lower()
    if suffix in PLAN_SUFFIXES:
        write_plan(mission, path)
    elif suffix in WPL_SUFFIXES:
        write_wpl(mission, path)
    else:
        raise MissionFileError(str(path), "", f"unknown mission file extension {suffix or '(none)'!r}; "
                                              f"expected .plan, .waypoints or .txt")


def convert_mission(source: str | Path, target: str | Path) -> Mission:
    """Read one file, check it holds what the target can carry, and write it in the format of the target's
    extension. Whether it flies is `mission validate`'s question, not the converter's."""
    mission = load_mission(source, flight=False)
    save_mission(mission, target)
    return mission
