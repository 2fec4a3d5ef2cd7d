"""Every MAV_CMD a mission may hold: the command catalogue validation is given.

A mission file may hold any command of MAVLink's common and ardupilotmega dialects (QGroundControl writes
SET_CAMERA_MODE for PX4, Mission Planner DO_AUX_FUNCTION, ArduPilot's tests NAV_SCRIPT_TIME); whether the vehicle
flies one is the vehicle's answer at upload. This package imports no pymavlink (it is a pure core), so the caller
passes the catalogue: NAC's commands pass `nac_onboard.mavlink.dialect.mission_catalogue()`, built from pymavlink's
MAV_CMD enum. MODEL_CATALOGUE, the default, knows only the commands missions.model names.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from missions.model import COMMAND_NAMES


@dataclass(frozen=True)
class DialectCommand:
    name: str  # without the MAV_CMD_ prefix, as QGC and MAVProxy print it
    has_location: bool  # params 5-7 are latitude, longitude, altitude


@dataclass(frozen=True)
class CommandCatalogue:
    """The commands of a MAVLink dialect by number, on top of the ones missions.model names."""

    commands: Mapping[int, DialectCommand] = field(default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "commands", MappingProxyType(dict(self.commands)))  # read-only, as the class

    def known(self, command: int) -> bool:
        return command in COMMAND_NAMES or command in self.commands

    def name(self, command: int) -> str:
        """The command's name: missions.model's, else the dialect's, else `command N`."""
        if command in COMMAND_NAMES:
            return COMMAND_NAMES[command]
        entry = self.commands.get(command)
        return entry.name if entry else f"command {command}"

    def entry(self, command: int) -> DialectCommand | None:
        """The dialect's description of the command (None for one only missions.model names)."""
        return self.commands.get(command)


#: The missions package's own table: the commands missions.model names, without a dialect's.
MODEL_CATALOGUE = CommandCatalogue()
