"""Mission model: items, frames and commands (stdlib only)."""

from missions.model import Frame, MavCmd, MissionItem, MissionType

__all__ = ["Frame", "MavCmd", "MissionItem", "MissionType"]
