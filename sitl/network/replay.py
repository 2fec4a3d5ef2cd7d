"""Links replayed from a recorded flight: each pair's measured throughput over time, interpolated, instead of
the radio model (`nac-sitl experiment --links replay:RUN`), so a real flight's links can be re-run against new
computing schemes.

A recording is a run directory whose probes say who measured whom, when and how much: NAC's own runs (SITL or
real vehicles, NAC's probes or iperf3's). Times are the probes' simulated seconds where the run has them (SITL:
both runs count from the simulator's start), else seconds since the recording's first probe. A failed probe
is a link with nothing through it. Before the first probe and after the last a pair keeps the end value.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nac_onboard.errors import BadInput

REPLAY_PREFIX = "replay:"


class ReplayError(BadInput):
    pass


@dataclass(frozen=True)
class ReplayLinks:
    source: str
    series: dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]  # unordered pair -> (t_s, bit/s)

    @classmethod
    def from_run(cls, run_dir: str | Path) -> ReplayLinks:
        from ground.logs.analysis import throughput
        from ground.logs.runlog import read_run

        path = Path(run_dir)
        if not path.is_dir():
            raise ReplayError(f"replay: {path} is not a run directory")
        probes = throughput(read_run(path), 0.0)
        probes = probes.dropna(subset=["client", "server"])
        if probes.empty:
            raise ReplayError(f"replay: {path} has no throughput probes to replay (expected agent throughput "
                              "records, as `nac-sitl experiment` or a flight writes them)")
        times = probes["t_sim_s"].astype(float)
        if times.isna().any():
            times = probes["t_s"].astype(float) - float(probes["t_s"].min())
        series: dict = {}
        for (a, b), rows in probes.assign(t=times).groupby(
                probes.apply(lambda r: tuple(sorted((str(r["client"]), str(r["server"])))), axis=1)):
            rows = rows.sort_values("t")
            series[(a, b)] = (rows["t"].to_numpy(float), rows["throughput_mbps"].to_numpy(float) * 1e6)
        return cls(str(path), series)

    def check_vehicles(self, ids: list[str]) -> None:
        unknown = sorted({v for pair in self.series for v in pair} - set(ids))
        if unknown:
            raise ReplayError(f"replay: {self.source} records vehicles {', '.join(unknown)} that the scenario "
                              f"does not fly (its vehicles: {', '.join(ids)})")

    def rate_bps(self, a: str, b: str, t_s: float) -> float | None:
        """The recorded throughput of the pair at t_s, interpolated; None when the pair was never measured."""
        found = self.series.get(tuple(sorted((a, b))))
        if found is None:
            return None
        return float(np.interp(t_s, found[0], found[1]))


def parse_links(text: str) -> ReplayLinks | None:
    """`model` (the radio model) or `replay:RUN`."""
    if text == "model":
        return None
    if text.startswith(REPLAY_PREFIX):
        return ReplayLinks.from_run(text[len(REPLAY_PREFIX):])
    raise ReplayError(f"--links: expected model or replay:RUN_DIR, got {text!r}")
