"""The one error the mission library raises for a bad file or mission."""

from __future__ import annotations

from nac_onboard.errors import BadInput


class MissionFileError(BadInput):
    """A mission file or mission that cannot be used, told the way an operator can fix it.

    str() is `SOURCE: WHERE: REASON`, e.g. `x.plan: item 4 (doJumpId 4): latitude 95.0 is outside -90..90`.
    """

    def __init__(self, source: str, where: str, reason: str):
        self.source, self.where, self.reason = str(source), where, reason
        super().__init__(": ".join(part for part in (self.source, where, reason) if part))
