"""The companion's door to pymavlink: MAVLink 2, the ardupilotmega dialect, names for numbers, the copter modes."""

from __future__ import annotations

import functools
import os

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink is imported: it defaults to MAVLink 1
from pymavlink import mavutil  # noqa: E402

from missions.dialect import CommandCatalogue, DialectCommand  # noqa: E402
from nac_onboard.mavlink.command_table import COMMANDS  # noqa: E402

M = mavutil.mavlink
COPTER_MODES = {name: number for number, name in mavutil.mode_mapping_acm.items()}


def enum_name(enum: str, value: int) -> str:
    """MAVLink's name of an enum value (MAV_RESULT 4 -> MAV_RESULT_FAILED), or the number when it has none."""
    entry = M.enums.get(enum, {}).get(value)
    return entry.name if entry is not None else str(value)


@functools.cache
def mission_catalogue() -> CommandCatalogue:
    """Every MAV_CMD of MAVLink's dialects, for mission validation (missions imports no pymavlink): pass it as
    `load_mission(path, catalogue=mission_catalogue())` or `validate(mission, source, catalogue=...)`. The
    definitions' own table (command_table.py) and the installed pymavlink's enum together: a mission may hold a
    command newer than the pymavlink release, and pymavlink may carry one the table's definitions have dropped."""
    commands = {number: DialectCommand(name, located) for number, (name, located) in COMMANDS.items()}
    commands.update({number: DialectCommand(entry.name.removeprefix("MAV_CMD_"),
                                            bool(getattr(entry, "has_location", False)))
                     for number, entry in M.enums["MAV_CMD"].items() if not entry.name.endswith("_ENUM_END")})
    return CommandCatalogue(commands)
