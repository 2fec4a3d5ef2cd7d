"""What each mechanism of the simulated air contributes to an iteration's time: `paper-flight-static` on the kernel
network with the mechanisms added one at a time, each run's pace beside the research's (640 iterations in 200 s).

    python benchmarks/mechanisms.py [--duration-s 60] [--speedup 1] [--smoke]

Variants, each a whole run (simulator, agents, MPI job, probes):
  htb             a rate class per pair, probes in classes of their own (the kernel network's default air)
  medium          every frame through the 802.11 medium: one FIFO queue per station, channel access, retries
  medium-probes-host-tcp  the same, with the probes back to back (iperf3-style, continuous) in the stations'
                  queues, both workers at once (a client per link), the companions' TCP this host's default (BBR)
  medium-probes   the same, the companions' TCP Reno (the flight scenarios' own: it keeps its results at 4x)
  medium-probes-in-turn  the same with the workers probed one at a time (the flight scenarios' schedule before)
  medium-probes-cubic  the same with a Jetson's TCP instead, CUBIC (Linux's default; its window grows with the
                  wall clock, so it is measured at 1x only)
  medium-probes-tx2  the same, with every rank's work at a Jetson TX2's CPU time (the shipped profile: this
                  host's single-thread 7-Zip score over the TX2's published one; `nac-onboard cpu-score`)
  medium-probes-device  the same, with every rank's work 100 times this host's CPU time (an illustration of a
                  much slower companion, not a device)
  medium-probes-sleep  medium-probes on the sleep network (as without root): no queues run, each round of the
                  master's inputs charged the mean of the queue the probes keep there (docs/radio.md)
Printed per variant: iterations, iterations per simulated minute, the median iteration and the iterations a
200 s static flight would hold at that pace, with the ratio to the research's 640. Needs root (namespaces).
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

from ground.logs.findings import PAPER_STATIC_ITERATIONS, PAPER_STATIC_S
from nac_onboard.compute.device import device_path, load_device_profile
from nac_onboard.flight_log import read_jsonl
from nac_onboard.records import kinds
from sitl.experiment.runner import Outcome, run_scenario
from sitl.experiment.scenario import load_scenario
from sitl.launcher import allocate_base_port

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

VARIANTS = ("htb", "medium", "medium-probes-host-tcp", "medium-probes", "medium-probes-in-turn", "medium-probes-cubic",
            "medium-probes-tx2", "medium-probes-device", "medium-probes-sleep")  # up to medium-probes each adds one
# mechanism to the one before; the rest each change medium-probes in one way: the probes in turn, a Jetson's TCP, a
# companion's CPU, or the sleep network's model of the air instead of the air
SMOKE = {"duration_s": 4.0, "speedup": 4.0, "variants": ["medium-probes"]}
ILLUSTRATIVE_SLOWDOWN = 100.0
ISOLATED_PROBE_S = 0.5  # the probes apart: 0.5 s every 2 s, one worker at a time, the schedule before issue 28


def variant(name: str, folder: Path, duration_s: float):
    """The shipped scenario (the medium, probes back to back) with the mechanisms the variant lacks taken out."""
    scenario = load_scenario("paper-flight-static")
    scenario = dataclasses.replace(scenario, duration_s=duration_s)
    air = "htb" if name == "htb" else "medium"
    tcp = "host" if name in ("htb", "medium", "medium-probes-host-tcp") else (
        "cubic" if name.endswith("-cubic") else "reno")
    scenario = dataclasses.replace(scenario, network=dataclasses.replace(scenario.network, air=air,
                                                                         congestion_control=tcp))
    probes = scenario.throughput
    back_to_back = name.startswith("medium-probes")
    scenario = dataclasses.replace(scenario, throughput=dataclasses.replace(
        probes, duration_s=probes.period_s if back_to_back else ISOLATED_PROBE_S,
        concurrent=back_to_back and not name.endswith("-in-turn")))
    if name.endswith("-tx2"):
        scenario = dataclasses.replace(scenario, compute=dataclasses.replace(
            scenario.compute, device=str(device_path("jetson-tx2"))))
        load_device_profile("jetson-tx2", measure_host=True)  # this host's score, measured once before the run
    if name.endswith("-device"):
        device = folder / "illustrative.toml"
        device.write_text(f'[device]\nname = "illustrative-{ILLUSTRATIVE_SLOWDOWN:g}x"\n'
                          f'slowdown = {ILLUSTRATIVE_SLOWDOWN}\nsource = "benchmarks/mechanisms.py: an '
                          f'illustration, not a measured device"\n')
        scenario = dataclasses.replace(scenario, compute=dataclasses.replace(scenario.compute, device=str(device)))
    return scenario


def measure(name: str, duration_s: float, speedup: float, folder: Path) -> dict:
    network = "sleep" if name.endswith("-sleep") else "kernel"
    result = run_scenario(variant(name, folder, duration_s), folder / name, speedup, allocate_base_port(3, slots=5),
                          out=io.StringIO(), network=network, figures=False)
    if result.outcome is not Outcome.COMPLETED:
        return {"variant": name, "outcome": result.outcome.name.lower(), "detail": result.detail, "ok": False}
    iterations = read_jsonl(kinds.COMPUTE_LOG.at(result.run_dir)).of_kind(kinds.ITERATION)
    durations = [r.get("duration_sim_s", r["duration_s"]) for r in iterations]
    per_min = result.summary.get("iterations_per_min")
    in_200_s = per_min * PAPER_STATIC_S / 60 if per_min else None
    return {"variant": name, "network": network, "outcome": result.outcome.name.lower(), "iterations": len(iterations),
            "iterations_per_sim_min": round(per_min, 1) if per_min else None,
            "median_iteration_s": round(float(np.median(durations)), 4) if durations else None,
            "iterations_in_200_s": round(in_200_s) if in_200_s else None,
            "versus_research_640": round(in_200_s / PAPER_STATIC_ITERATIONS, 2) if in_200_s else None,
            "air_late_share": result.summary.get("air_late_share"),
            "ok": result.outcome is Outcome.COMPLETED}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration-s", type=float, default=60.0, help="simulated seconds per run")
    parser.add_argument("--speedup", type=float, default=1.0)
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    args = _common.parse_args(parser, SMOKE)
    folder = _common.kernel_runs_folder("mechanisms", "nac-bench-mech-")
    if folder is None:
        return 2
    try:
        runs = [measure(name, args.duration_s, args.speedup, folder) for name in args.variants]
        for run in runs:
            print(json.dumps({"mechanism": run}), flush=True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0 if all(r["ok"] for r in runs) else 1


if __name__ == "__main__":
    sys.exit(main())
