"""The one error the mission library raises for a bad file or mission.

The library imports the standard library only, so its error is its own (a ValueError), not one of NAC's error base
(nac_onboard.errors): NAC's command lines (`run_cli`) take it as bad input, exit 2, and print its message.
"""

from __future__ import annotations

EXIT_BAD_INPUT = 2  # as nac_onboard.errors.BadInput


class MissionFileError(ValueError):
    """A mission file or mission that cannot be used, told the way an operator can fix it.

    str() is `SOURCE: WHERE: REASON`, e.g. `x.plan: item 4 (doJumpId 4): latitude 95.0 is outside -90..90`.
    """

    exit_code = EXIT_BAD_INPUT

    def __init__(self, source: str, where: str, reason: str):
        self.source, self.where, self.reason = str(source), where, reason
        super().__init__(": ".join(part for part in (self.source, where, reason) if part))
