"""Links replayed from a recorded flight: each pair's measured throughput over time, interpolated, in place of
the radio model where the recording has the pair (`nac-sitl experiment --links replay:RUN`; the runner builds
the table from the run's probes, sitl.network.replay). Both networks read it: the kernel shaper, and the sleep
emulation through the channel's `replay_file` (a JSON file the runner writes beside the run's channel; read and
written by nac_onboard.radio.files, as the JSON this module turns into a table and back).

Times are simulated seconds (both SITL runs count from the simulator's start) or, for a recording without
them, seconds since its first probe. Before a pair's first probe and after its last the end value holds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nac_onboard.errors import BadInput

EXPECTED_JSON = '{"source": "...", "pairs": [{"a": "master", "b": "w1", "t_s": [...], "rate_bps": [...]}]}'


class ReplayError(BadInput):
    pass


@dataclass(frozen=True)
class ReplayLinks:
    source: str
    series: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]  # unordered pair -> (t_s, bit/s)

    def check_vehicles(self, ids: list[str]) -> None:
        unknown = sorted({v for pair in self.series for v in pair} - set(ids))
        if unknown:
            raise ReplayError(f"replay: {self.source} records vehicles {', '.join(unknown)} that the scenario "
                              f"does not fly (its vehicles: {', '.join(ids)})")

    def rate_bps(self, a: str, b: str, t_s: float) -> float | None:
        """The recorded throughput of the pair at t_s, interpolated; None when the pair was never measured."""
        found = self.series.get((a, b) if a <= b else (b, a))
        if found is None:
            return None
        return float(np.interp(t_s, found[0], found[1]))

    def to_json(self) -> dict:
        pairs = [{"a": a, "b": b, "t_s": t.tolist(), "rate_bps": r.tolist()} for (a, b), (t, r) in self.series.items()]
        return {"source": self.source, "pairs": pairs}

    @classmethod
    def from_json(cls, data, where: str) -> ReplayLinks:
        """A table from its JSON (as to_json gives it); where: what to name in an error (the file)."""
        try:
            series = {}
            for k, pair in enumerate(data["pairs"]):
                t, rate = np.asarray(pair["t_s"], float), np.asarray(pair["rate_bps"], float)
                a, b = sorted((str(pair["a"]), str(pair["b"])))
                if t.ndim != 1 or t.shape != rate.shape or len(t) == 0 or np.any(np.diff(t) < 0) or \
                        not (np.isfinite(t).all() and np.isfinite(rate).all() and (rate >= 0).all()):
                    raise ValueError(f"pair {k + 1}: t_s and rate_bps must be equal-length lists of finite "
                                     "numbers, times rising, rates >= 0")
                series[(a, b)] = (t, rate)
            return cls(str(data.get("source", where)), series)
        except (ValueError, KeyError, TypeError, AttributeError) as err:
            raise ReplayError(f"{where}: not a replay table (expected {EXPECTED_JSON}): {err}") from None
