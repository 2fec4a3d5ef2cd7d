"""Mission model: items, frames and commands; QGC .plan and QGC WPL 110 files; validation (stdlib only)."""

from missions.errors import MissionFileError
from missions.files import convert_mission, load_mission, loads_mission, save_mission
from missions.model import (
    Frame,
    MavCmd,
    Mission,
    MissionItem,
    MissionType,
    PlanInfo,
    PlanItemInfo,
    PlannedHome,
)
from missions.plan import dumps_plan, loads_plan, read_plan, write_plan
from missions.validate import validate
from missions.wpl import dumps_wpl, loads_wpl, read_wpl, write_wpl

__all__ = [
    "Frame", "MavCmd", "Mission", "MissionFileError", "MissionItem", "MissionType", "PlanInfo", "PlanItemInfo",
    "PlannedHome", "convert_mission", "dumps_plan", "dumps_wpl", "load_mission", "loads_mission", "loads_plan",
    "loads_wpl", "read_plan", "read_wpl", "save_mission", "validate", "write_plan", "write_wpl",
]
