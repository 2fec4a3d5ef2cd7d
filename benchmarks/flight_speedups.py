"""Whether a flight scenario's results depend on the speed-up (issue 28, acceptance 3): the scenario run --runs times
at each speed-up on the kernel network (speed-ups taken in turn, so a drift of the host's load falls on each), then
per worker, over every distance and per 2 m bin, the time per 10 iterations and the probes' throughput pooled over
the runs and compared: medians with their 95 % intervals (ground.logs.agreement; a bin with fewer than 8 samples in
either set is not judged). One run of the moving flight holds one or two blocks of 10 iterations per 2 m bin, so
bins are judged only over several runs.

    python benchmarks/flight_speedups.py [--scenarios paper-flight-moving ...] [--speedups 1 4] [--runs 3]
        [--duration-s S] [--smoke]

Printed: a line per run (iterations per simulated minute, Spearman rho of w1's time per 10 with its distance over the
run and before w1's first link loss), a line per judged quantity and bin (both medians, their ratio, whether they can
agree within 10 %), and a line per scenario (the runs' mean iterations per simulated minute at each speed-up and their
ratio; rho before the link loss over each speed-up's runs pooled, with its 95 % interval). Needs root.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import shutil
import sys
from pathlib import Path

import numpy as np

from ground.logs import iteration_pace
from ground.logs.agreement import compare, pooled_rho_before_loss, pooled_tables
from sitl.experiment.runner import Outcome, run_scenario
from sitl.experiment.scenario import load_scenario
from sitl.launcher import allocate_base_port

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SCENARIOS = ("paper-flight-moving", "paper-flight-static")
SMOKE = {"scenarios": ["paper-flight-static"], "speedups": [4.0, 8.0], "runs": 1, "duration_s": 4.0}


def one_run(name: str, speedup: float, duration_s: float | None, folder: Path) -> dict:
    scenario = load_scenario(name)
    if duration_s is not None:
        scenario = dataclasses.replace(scenario, duration_s=duration_s)
    result = run_scenario(scenario, folder, speedup, allocate_base_port(3, slots=5), out=io.StringIO(),
                          network="kernel", figures=False)
    summary = result.summary or {}
    return {"scenario": name, "speedup": speedup, "outcome": result.outcome.name.lower(),
            "ok": result.outcome is Outcome.COMPLETED, "run_dir": str(folder),
            "iterations": summary.get("iterations"),
            "iterations_per_sim_min": _round(summary.get("iterations_per_min")),
            "rho_w1": _round((summary.get("time_per_10_spearman") or {}).get("w1"), 3),
            "rho_w1_before_loss": _round((summary.get("time_per_10_spearman_before_loss") or {}).get("w1"), 3),
            "blocks_w1_before_loss": (summary.get("time_per_10_blocks_before_loss") or {}).get("w1")}


def judged(name: str, runs: list[dict], speedups: list[float]) -> list[dict]:
    sets = [[r["run_dir"] for r in runs if r["speedup"] == s and r["ok"]] for s in speedups]
    if not all(sets):
        return []
    lines = []
    for row in compare((pooled_tables(sets[0]), pooled_tables(sets[1]))):
        lines.append({"scenario": name, "quantity": row.quantity, "worker": row.worker,
                      "distance_from_m": row.distance_from_m if row.distance_from_m is not None else "all",
                      "samples": list(row.samples), "medians": [_round(m, 3) for m in row.medians],
                      "ratio": _round(row.ratio, 3), "can_agree_within_10_percent": row.agrees})
    return lines


def _pooled_rho(pooled: tuple[float, int] | None) -> dict | None:
    """A pooled rho with its blocks and 95 % interval."""
    if pooled is None:
        return None
    rho, blocks = pooled
    return {"rho": _round(rho, 3), "blocks": blocks,
            "interval_95": [_round(x, 3) for x in iteration_pace.spearman_interval(rho, blocks)]}


def _round(value, digits: int = 1):
    return None if value is None or not np.isfinite(value) else round(float(value), digits)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenarios", nargs="+", choices=SCENARIOS, default=list(SCENARIOS))
    parser.add_argument("--speedups", type=float, nargs=2, default=[1.0, 4.0])
    parser.add_argument("--runs", type=int, default=3, help="runs at each speed-up")
    parser.add_argument("--duration-s", type=float, default=None, help="simulated seconds (default: the scenario's)")
    args = _common.parse_args(parser, SMOKE)
    folder = _common.kernel_runs_folder("flight_speedups", "nac-bench-speedups-")
    if folder is None:
        return 2
    ok = True
    try:
        for name in args.scenarios:
            runs = []
            for k in range(args.runs):
                for speedup in args.speedups:
                    run = one_run(name, speedup, args.duration_s, folder / f"{name}-{speedup:g}x-{k}")
                    print(json.dumps({"run": {key: v for key, v in run.items() if key != "run_dir"}}), flush=True)
                    runs.append(run)
            ok = ok and all(r["ok"] for r in runs)
            for line in judged(name, runs, args.speedups):
                print(json.dumps({"agreement": line}), flush=True)
            pace = [[r["iterations_per_sim_min"] for r in runs if r["speedup"] == s and r["iterations_per_sim_min"]]
                    for s in args.speedups]
            means = [_round(np.mean(p)) if p else None for p in pace]
            pooled = [pooled_rho_before_loss([r["run_dir"] for r in runs if r["speedup"] == s and r["ok"]], "w1")
                      for s in args.speedups]
            print(json.dumps({"scenario": {"name": name, "speedups": args.speedups, "runs": args.runs,
                                           "mean_iterations_per_sim_min": means,
                                           "ratio": _round(means[1] / means[0], 3) if all(means) else None,
                                           "pooled_rho_w1_before_loss": [_pooled_rho(p) for p in pooled]}}),
                  flush=True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
