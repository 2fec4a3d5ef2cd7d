"""The companion's door to pymavlink: MAVLink 2, the ardupilotmega dialect, names for numbers, the copter modes."""

from __future__ import annotations

import functools
import os

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is imported: it defaults to MAVLink 1
from pymavlink import mavutil  # noqa: E402

from missions.dialect import CommandCatalogue, DialectCommand  # noqa: E402

M = mavutil.mavlink
COPTER_MODES = {name: number for number, name in mavutil.mode_mapping_acm.items()}


def enum_name(enum: str, value: int) -> str:
    """MAVLink's name of an enum value (MAV_RESULT 4 -> MAV_RESULT_FAILED), or the number when it has none."""
    entry = M.enums.get(enum, {}).get(value)
    return entry.name if entry is not None else str(value)


@functools.cache
def mission_catalogue() -> CommandCatalogue:
    """Every MAV_CMD of the dialect, for mission validation (missions imports no pymavlink): pass it as
    `load_mission(path, catalogue=mission_catalogue())` or `validate(mission, source, catalogue=...)`."""
    return CommandCatalogue({number: DialectCommand(entry.name.removeprefix("MAV_CMD_"),
                                                    bool(getattr(entry, "has_location", False)))
                             for number, entry in M.enums["MAV_CMD"].items() if not entry.name.endswith("_ENUM_END")})
