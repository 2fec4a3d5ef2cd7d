"""Every MAV_CMD the MAVLink dialects in use define: a catalogue the MAVLink adapter fills.

A mission file may hold any command of MAVLink's common and ardupilotmega dialects (QGroundControl writes
SET_CAMERA_MODE for PX4, Mission Planner DO_AUX_FUNCTION, ArduPilot's tests NAV_SCRIPT_TIME); whether the vehicle
flies one is the vehicle's answer at upload. This package imports no pymavlink (it is a pure core): the adapter
that does, `nac_onboard.mavlink.dialect`, registers pymavlink's MAV_CMD enum here when it is imported, as every
NAC command that reads mission files does. Without it the catalogue is the commands missions.model names.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from missions.model import COMMAND_NAMES


@dataclass(frozen=True)
class DialectCommand:
    name: str  # without the MAV_CMD_ prefix, as QGC and MAVProxy print it
    has_location: bool  # params 5-7 are latitude, longitude, altitude


_catalogue: dict[int, DialectCommand] = {}


def register_commands(commands: Mapping[int, DialectCommand]) -> None:
    _catalogue.update(commands)


def dialect_commands() -> Mapping[int, DialectCommand]:
    return _catalogue


def known_command(command: int) -> bool:
    return command in COMMAND_NAMES or command in _catalogue


def dialect_name(command: int) -> str:
    """The command's name: missions.model's, else the dialect's, else `command N`."""
    if command in COMMAND_NAMES:
        return COMMAND_NAMES[command]
    entry = _catalogue.get(command)
    return entry.name if entry else f"command {command}"
