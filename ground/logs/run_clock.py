"""The time axis of a run's tables and figures: seconds since the run's first record, on the run's own clock (pure).

Every NAC record carries unix seconds (`t_s`), the wall clock of whoever wrote it. On a vehicle that is the flight's
time; in SITL at `--speedup 4` a 130 s flight spans 33 wall seconds, and a figure on wall time would show a
sped-up run's flight four times shorter than the same run at 1x and than the research's figures. A SITL run's
records pair the two clocks: the shaper's `link_rates` (kernel network, every 0.1 simulated s) and the energy
meter's records (every SITL run, each vehicle each simulated second) carry `t_sim_s` beside `t_s`. Between paired
points a time is interpolated, beyond them extrapolated at the run's mean pace; a run without pairs (a real
flight, or files from other tools) keeps its wall seconds, which are its flight's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nac_onboard.flight_log import finite_number

MIN_PAIRS = 2


def clock_pairs(records: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """(wall, simulated) seconds of the records carrying both numbers, in wall order, one per wall time, the
    simulated ones never going back (one writer's records; another's lag cannot reverse its clock)."""
    pairs = sorted({float(r["t_s"]): float(r["t_sim_s"]) for r in records
                    if finite_number(r.get("t_s")) and finite_number(r.get("t_sim_s"))}.items())
    if len(pairs) < MIN_PAIRS:
        return np.empty(0), np.empty(0)
    wall, sim = (np.array(column) for column in zip(*pairs, strict=True))
    return wall, np.maximum.accumulate(sim)


@dataclass(frozen=True)
class RunClock:
    t0_s: float  # unix seconds of the run's first record: 0 on the axis
    wall_s: np.ndarray  # paired points (empty: the axis is wall seconds)
    sim_s: np.ndarray

    @classmethod
    def of(cls, t0_s: float, *sources: list[dict]) -> RunClock:
        """The clock from the first source holding enough pairs (the most frequent first)."""
        for records in sources:
            wall, sim = clock_pairs(records)
            if len(wall) and wall[-1] > wall[0] and sim[-1] > sim[0]:
                return cls(t0_s, wall, sim)
        return cls(t0_s, np.empty(0), np.empty(0))

    @property
    def simulated(self) -> bool:
        """Whether the axis is the run's simulated time (False: wall seconds)."""
        return len(self.wall_s) >= MIN_PAIRS

    def _sim_at(self, t_s: np.ndarray) -> np.ndarray:
        pace = (self.sim_s[-1] - self.sim_s[0]) / (self.wall_s[-1] - self.wall_s[0])
        out = np.interp(t_s, self.wall_s, self.sim_s)
        before, after = t_s < self.wall_s[0], t_s > self.wall_s[-1]
        out[before] = self.sim_s[0] - (self.wall_s[0] - t_s[before]) * pace
        out[after] = self.sim_s[-1] + (t_s[after] - self.wall_s[-1]) * pace
        return out

    def rel_s(self, t_s):
        """Seconds since the run's first record on its clock, for one unix time or an array of them."""
        times = np.asarray(t_s, dtype=float)
        flat = np.atleast_1d(times)
        if self.simulated:
            out = self._sim_at(flat) - self._sim_at(np.array([self.t0_s]))[0]
        else:
            out = flat - self.t0_s
        return float(out[0]) if times.ndim == 0 else out
