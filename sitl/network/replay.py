"""`--links replay:RUN`: a recorded run's links as a replay table (nac_onboard.radio.replay), so a real flight's
links can be re-run against new computing schemes.

A recording is a run directory whose probes say who measured whom, when and how much: NAC's own runs (SITL or
real vehicles, NAC's probes or iperf3's). Times are the probes' simulated seconds where the run has them (SITL:
both runs count from the simulator's start), else seconds since the recording's first probe. A failed probe
is a link with nothing through it. Before the first probe and after the last a pair keeps the end value.
"""

from __future__ import annotations

from pathlib import Path

from nac_onboard.radio.replay import ReplayError, ReplayLinks

REPLAY_PREFIX = "replay:"


def replay_from_run(run_dir: str | Path) -> ReplayLinks:
    """Each pair's probes of a recorded run as a replay table."""
    from ground.logs.analysis import throughput
    from ground.logs.run_clock import RunClock
    from ground.logs.runlog import read_run

    path = Path(run_dir)
    if not path.is_dir():
        raise ReplayError(f"replay: {path} is not a run directory")
    probes = throughput(read_run(path), RunClock.of(0.0))  # its times from t_sim_s or t_s, below
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
    return ReplayLinks(str(path), series)


def parse_links(text: str) -> ReplayLinks | None:
    """`model` (the radio model) or `replay:RUN`."""
    if text == "model":
        return None
    if text.startswith(REPLAY_PREFIX):
        return replay_from_run(text[len(REPLAY_PREFIX):])
    raise ReplayError(f"--links: expected model or replay:RUN_DIR, got {text!r}")
