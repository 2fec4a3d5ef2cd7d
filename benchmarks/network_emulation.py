"""The kernel network of SITL experiments: how exactly it shapes, how fast it follows the vehicles, and what a
whole run costs on this machine (needs root, ip, tc, nft and iperf3).

0. The frame-level air (delay line): a small message's round trip against the medium model's, at each speed-up,
   beside the same echo over a bare veth pair (the host's floor), and the delay line's CPU per 1,000 packets a
   second while iperf3 sends through it.
1. Shaping accuracy: real iperf3 (3 s) through a shaped pair at 1, 10 and 50 Mbit/s: received / target.
2. Shaper update latency: a position change, until the kernel's HTB class holds the new rate (read back with
   `tc class show`): the shaper's write plus tc's apply.
3. Whole runs: a fleet of 3, 8 and 16 vehicles (master hovering, workers around it, half of them flying in and
   out), linreg over the kernel network with probes, at 1x and at 4x (`--speedups`: each against the first):
   wall time, CPU, and the results in simulated time (iterations per simulated minute, mean probe throughput).
   Target: 8 vehicles at 4x within 10 % of the 1x run. `--air medium`: the flight scenarios' air instead;
   `--device`: the companions' device profile; `--probes none`: the job alone. Each ratio also comes window by
   window (`by_window_ratio_95`: the ratio over the windows both runs hold and its 95 % interval), for one run's pace
   is only as steady as its windows are.

    python benchmarks/network_emulation.py [--rates 1 10 50] [--fleets 3 8 16] [--duration-s 60] [--speedups 1 4]
                                           [--air htb|medium] [--device jetson-tx2] [--probes in-turn|none]
                                           [--smoke]
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import math
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import pandas as pd

from ground.logs.agreement import pace_by_window, ratio_interval
from missions import save_mission
from nac_onboard.clock import publish as publish_clock
from nac_onboard.flight_log import JsonlLog, read_jsonl
from nac_onboard.radio.channel import PRESETS, ChannelModel
from nac_onboard.radio.medium import MacTiming, expected_echo_s
from nac_onboard.records import kinds
from sitl.experiment.runner import Outcome, run_scenario
from sitl.experiment.scenario import load_scenario
from sitl.network.air import AirNetwork
from sitl.network.medium_air import MediumAir
from sitl.network.netns import (
    delete_namespace,
    new_prefix,
    run,
    udp_echo_round_trips,
)
from sitl.network.shaper import Shaper
from sitl.scenarios.generate import at, hover, route

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

# --smoke leaves out the whole runs (15-20 s of the suite's time): they are run_scenario, which mechanisms.py's smoke
# and the experiment tests run already; only the generated fleet's scenario is left to the full run
SMOKE = {"rates": [10.0], "fleets": [], "speedups": [4.0], "duration_s": 8.0, "latency_samples": 5,
         "iperf_s": 1}


def capped(rate_mbps: float) -> ChannelModel:
    """A link of exactly rate_mbps at 2 m: Shannon's rate (far above it there) capped, nothing taken off it. The cap
    is a Shannon-model field: wifi-flight's own 802.11n rates would give MCS 7 x its MAC efficiency (39 Mbit/s)."""
    return dataclasses.replace(PRESETS["wifi-flight"], name=f"capped-{rate_mbps:g}", rate_model="shannon",
                               max_rate_bps=rate_mbps * 1e6, min_rate_bps=0.0, mac_efficiency=1.0,
                               shadowing_sigma_db=0.0, rician_k_db=None)


def shaping_accuracy(rate_mbps: float, seconds: int, folder: Path) -> dict:
    near = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    air = AirNetwork(["a", "b"], ap=None, sharing=False).create()
    try:
        with JsonlLog(folder / "accuracy.jsonl") as out:
            shaper = Shaper(air, lambda: (0.0, near), capped(rate_mbps), 1.0, 0.1, out).start()
            server = subprocess.Popen([*air.exec_prefix(1), "iperf3", "--server", "--one-off", "--forceflush"],
                                      stdout=subprocess.PIPE, text=True)
            server.stdout.readline()
            server.stdout.readline()
            done = subprocess.run([*air.exec_prefix(0), "iperf3", "--client", air.stations[1].address, "--time",
                                   str(seconds), "--json"], capture_output=True, text=True, timeout=60)
            server.wait(10)
            shaper.stop()
    finally:
        air.close()
    received = json.loads(done.stdout)["end"]["sum_received"]["bits_per_second"]
    return {"target_mbps": rate_mbps, "iperf3_mbps": round(received / 1e6, 3),
            "ratio": round(received / (rate_mbps * 1e6), 3)}


def update_latency(samples: int, folder: Path) -> dict:
    """Each sample moves b so its rate changes, then reads the class until the kernel reports the new rate."""
    air = AirNetwork(["a", "b"], ap=None, sharing=False).create()
    position = {"b": 4.0}
    latencies = []
    try:
        with JsonlLog(folder / "latency.jsonl") as out:
            shaper = Shaper(air, lambda: (0.0, np.array([[0.0, 0.0, 0.0], [position["b"], 0.0, 0.0]])),
                            PRESETS["wifi-flight"], 1.0, 3600.0, out).start()  # updated by hand below
            port = air.stations[1].port
            for k in range(samples):
                position["b"] = 8.0 + (k % 2) * 4.0
                t0 = time.monotonic()
                state = shaper.update()
                want = state.class_bps(0, 1)
                while True:
                    text = subprocess.run(["tc", "-n", air.air_ns, "class", "show", "dev", port, "classid",
                                           "1:100"], capture_output=True, text=True).stdout
                    shown = _rate_bps(text)
                    if shown is not None and abs(shown - want) <= 0.01 * want:  # tc rounds what it shows
                        break
                    if time.monotonic() - t0 > 5.0:
                        raise RuntimeError(f"the class did not take {want} bit/s: {text}")
                latencies.append(time.monotonic() - t0)
            shaper.stop()
    finally:
        air.close()
    return {"samples": samples, "median_ms": round(1000 * statistics.median(latencies), 2),
            "max_ms": round(1000 * max(latencies), 2),
            "note": "includes one `tc class show` process start per reading"}


def _rate_bps(tc_text: str) -> int | None:
    match = re.search(r" rate (\d+(?:\.\d+)?)([KMG]?)bit", tc_text)
    if not match:
        return None
    scale = {"": 1, "K": 1e3, "M": 1e6, "G": 1e9}[match.group(2)]
    return int(round(float(match.group(1)) * scale))


PROBE_PERIOD_S = 2.0  # the fleet's probes, one worker after another: a cycle is (vehicles - 1) x this
WINDOW_S = 10.0  # without probes, a run's pace is taken window by window over this many simulated seconds, or
# over WINDOWS_A_RUN of a shorter run's duration: a 15 s run's job computes for some 12 s after the take-off, which
# 10 s windows leave without a ratio's interval (MIN_WINDOWS whole windows in common)
WINDOWS_A_RUN = 8


def fleet_scenario(folder: Path, vehicles: int, duration_s: float, air: str = "htb", device: str = "host",
                   probes: bool = True) -> Path:
    """Master at the origin; workers on rings 6-10 m out, every other one flying out to 14 m and back: always in
    range, and with a timeout no iteration reaches, so the comparison measures the clock, not a threshold (a
    worker whose iterations take about the timeout flips between late and absent, run to run). air "medium": the
    flight scenarios' air (the 802.11 medium, Reno), the workers probed back to back one at a time: fifteen bulk
    flows at once through one medium saturate it (0.87 of it busy, 13 % of exchanges colliding, seconds of queue at
    every station), so that the probes' connections time out and an iteration takes 5 s. device: the companions'
    device profile (their CPU time stretched to it, nac_onboard.compute.device); probes False: none at all."""
    folder.mkdir(parents=True, exist_ok=True)
    save_mission(hover(at(0, 0), 3.0), folder / "v0.plan")
    probe_table = ["[throughput]", f"period_s = {PROBE_PERIOD_S}",
                   "duration_s = 0.5" if air == "htb" else "duration_s = 1.0", "interval_s = 0.1"]
    blocks = ['name = "fleet"', f"duration_s = {duration_s}", "max_speedup = 8.0", '[channel]',
              'preset = "wifi-flight"', "[compute]", 'task = "linreg"', "timeout_s = 20.0", f'device = "{device}"',
              *(probe_table if probes else []), "[network]", f'air = "{air}"',
              'congestion_control = "host"' if air == "htb" else 'congestion_control = "reno"',
              '[[vehicle]]', 'id = "v0"', 'role = "master"', 'mission = "v0.plan"']
    for k in range(1, vehicles):
        angle = 2 * math.pi * k / (vehicles - 1)
        radius = 6.0 + 2.0 * (k % 3)
        east, north = radius * math.cos(angle), radius * math.sin(angle)
        if k % 2:
            mission = route(at(east, north), 3.0, [(east * 14 / radius, north * 14 / radius), (east, north)],
                            speed_mps=0.5)
        else:
            mission = hover(at(east, north), 3.0)
        save_mission(mission, folder / f"v{k}.plan")
        blocks += ['[[vehicle]]', f'id = "v{k}"', 'role = "worker"', f'mission = "v{k}.plan"']
    (folder / "fleet.toml").write_text("\n".join(blocks) + "\n")
    return folder / "fleet.toml"


def whole_run(vehicles: int, speedup: float, duration_s: float, folder: Path, air: str = "htb", device: str = "host",
              probes: bool = True) -> dict:
    """One run of the fleet; its pace also window by window (iterations per simulated minute in each whole window
    of WINDOW_S or less, or of one cycle of the probes in turn), from which a ratio of two runs gets its interval;
    and the wall time to the job's go (the MPI job's start-up, the missions' upload, the take-off: all on the run's
    clock)."""
    scenario = load_scenario(str(fleet_scenario(folder / f"fleet-{vehicles}-{air}", vehicles, duration_s, air,
                                                device, probes)))
    before_self, before_children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(
        resource.RUSAGE_CHILDREN)
    t0, t0_unix = time.monotonic(), time.time()
    from sitl.launcher import allocate_base_port

    run_dir = folder / f"run-{vehicles}-{air}-{speedup:g}x"
    result = run_scenario(scenario, run_dir, speedup, allocate_base_port(vehicles, slots=5), out=io.StringIO(),
                          network="kernel", figures=False)
    wall_s = time.monotonic() - t0
    after_self, after_children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(
        resource.RUSAGE_CHILDREN)
    cpu = sum(getattr(after, f) - getattr(before, f) for after, before in
              ((after_self, before_self), (after_children, before_children)) for f in ("ru_utime", "ru_stime"))
    s = result.summary
    compute_log = kinds.COMPUTE_LOG.at(run_dir)
    started = read_jsonl(compute_log).of_kind(kinds.STARTED) if compute_log.exists() else []
    window_s = (vehicles - 1) * PROBE_PERIOD_S if probes else min(WINDOW_S, duration_s / WINDOWS_A_RUN)
    iterations = run_dir / "analysis" / "iterations.csv"
    by_window = pace_by_window(pd.read_csv(iterations), window_s) if iterations.exists() else pd.Series(dtype=float)
    return {"vehicles": vehicles, "air": air, "speedup": speedup, "outcome": result.outcome.name.lower(),
            "wall_s": round(wall_s, 1),
            "wall_to_go_s": round(started[0]["t_s"] - t0_unix, 1) if started else None,
            "cpu_s": round(cpu, 1), "cpu_cores": round(cpu / wall_s, 2),
            "iterations": s.get("iterations"), "iterations_per_sim_min": _round(s.get("iterations_per_min")),
            "window_s": window_s, "iterations_per_sim_min_by_window": {f"{t:g}": round(x, 1) for t, x in
                                                                       by_window.items()},
            "mean_throughput_mbps": _round(s.get("mean_throughput_mbps")),
            "measured_to_applied_by_bin": s.get("measured_to_applied_by_bin"),
            "ok": result.outcome is Outcome.COMPLETED}


def _interval(first: dict, second: dict) -> list[float] | None:
    """The second run's pace over the first's over the windows both hold, with its 95 % interval."""
    first_s, second_s = (pd.Series({float(t): x for t, x in run["iterations_per_sim_min_by_window"].items()})
                         for run in (first, second))
    found = ratio_interval(first_s, second_s)
    return None if found is None else [round(x, 3) for x in found]


def _round(value):
    return None if value is None else round(float(value), 2)


def delay_line(speedup: float, samples: int, iperf_s: int, folder: Path) -> dict:
    """The frame-level air (`[network] air = "medium"`) between two stations at 30 Mbit/s PHY: a 100-byte UDP echo's
    round trip (simulated seconds) against the medium model's for an echo answered at once (expected_echo_s) and
    against this host's floor (the same echo over a bare veth pair, times the speed-up), the lead the delay line
    took off each delivery and how late (wall) it wrote the echo's frames all the same, and its CPU while iperf3
    sends through it, per 1,000 packets a second it carries (offload runs counted as the packets they stand for)."""
    phy_bps = 30e6
    clock_path = folder / f"clock-{speedup:g}.json"
    publish_clock(str(clock_path), speedup, 0.0)
    air = MediumAir(["a", "b"], ap=0, sharing=True, speedup=speedup, clock_path=clock_path).create()
    a, b = air.stations
    try:
        rates = np.array([[0.0, phy_bps], [phy_bps, 0.0]])
        air.apply(types.SimpleNamespace(frames={"phy_bps": rates, "per": np.zeros((2, 2))}), speedup)
        rtts = _echo(a.netns, b.netns, b.address, samples, speedup)
        lead_s, echo_late_s = air.lead_s, _next_counters(air, air.counters).get("late_p50_s")
        iperf = subprocess.Popen([*air.exec_prefix(1), "iperf3", "-s", "-1", "-B", b.address],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.3)
        cpu0, t0, packets0 = _cpu_s(air.line.pid), time.monotonic(), _carried(air)
        sent = subprocess.run([*air.exec_prefix(0), "iperf3", "-c", b.address, "-t", str(iperf_s), "--json"],
                              capture_output=True, text=True, timeout=60 + iperf_s)
        time.sleep(1.1)  # the delay line's next counters line
        cpu_s, wall_s, packets = _cpu_s(air.line.pid) - cpu0, time.monotonic() - t0, _carried(air) - packets0
        iperf.wait(10)
    finally:
        air.close()
    model_s = expected_echo_s(MacTiming(), 128, phy_bps)
    measured = sorted(rtts)
    floor = statistics.median(_plain_veth_echo(samples))
    cpu_pct = 100 * cpu_s / wall_s
    rate = packets / wall_s
    mbps = json.loads(sent.stdout)["end"]["sum_received"]["bits_per_second"] / speedup / 1e6 if sent.stdout else None
    median = statistics.median(measured)
    return {"speedup": speedup, "rtt_median_ms": round(median * 1e3, 3),
            "rtt_p90_ms": round(measured[int(0.9 * (len(measured) - 1))] * 1e3, 3),
            "model_ms": round(model_s * 1e3, 3), "rtt_ratio": round(median / model_s, 3),
            "lead_ms": round(lead_s * 1e3, 3),
            "echo_late_p50_us_wall": None if echo_late_s is None else round(echo_late_s / speedup * 1e6, 1),
            "plain_veth_ms": round(floor * 1e3, 3), "plain_veth_simulated_ms": round(floor * speedup * 1e3, 3),
            "iperf3_mbps_simulated": mbps and round(mbps, 2),
            "packets_per_s": round(rate), "cpu_pct": round(cpu_pct, 1),
            "cpu_pct_per_1000_pps": round(cpu_pct / (rate / 1000), 2) if rate else None}


def _next_counters(air: MediumAir, seen: dict | None, timeout_s: float = 3.0) -> dict:
    """The delay line's next counters line after `seen` (one a wall second: its medians are the last second's)."""
    deadline = time.monotonic() + timeout_s
    while air.counters is seen and time.monotonic() < deadline:
        time.sleep(0.05)
    return air.counters or {}


def _echo(client_ns: str, server_ns: str, server_address: str, samples: int, speedup: float = 1.0) -> list[float]:
    """A 100-byte UDP echo's round trips (simulated seconds: wall x speed-up), both ends in this one thread, after
    5 not counted."""
    wall = udp_echo_round_trips(client_ns, server_ns, server_address, samples + 5, 0.005, 5.0)
    return [r * speedup for r in wall[5:]]


def _plain_veth_echo(samples: int) -> list[float]:
    """The same echo between two namespaces joined by a bare veth pair: this host's own floor (its stack and the
    echo's Python), which no emulator on wall time goes below, and which a speed-up multiplies."""
    prefix = new_prefix()
    a, b = f"{prefix}-pa", f"{prefix}-pb"
    try:
        for name in (a, b):
            run(["ip", "netns", "add", name], "plain veth")
        run(["ip", "link", "add", "veth0", "netns", a, "type", "veth", "peer", "name", "veth0", "netns", b],
            "plain veth")
        for name, address in ((a, "10.99.0.1/24"), (b, "10.99.0.2/24")):
            run(["ip", "-n", name, "addr", "add", address, "dev", "veth0"], "plain veth")
            run(["ip", "-n", name, "link", "set", "veth0", "up"], "plain veth")
        return _echo(a, b, "10.99.0.2", samples)
    finally:
        for name in (a, b):
            delete_namespace(name)


def _cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _carried(air: MediumAir) -> int:
    """Packets the medium has carried so far (its last counters line), offload runs as their segments."""
    return (air.counters or {}).get("segments_delivered", 0)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rates", type=float, nargs="+", default=[1.0, 10.0, 50.0], help="Mbit/s")
    parser.add_argument("--fleets", type=int, nargs="+", default=[3, 8, 16])
    parser.add_argument("--speedups", type=float, nargs="+", default=[1.0, 4.0])
    parser.add_argument("--duration-s", type=float, default=60.0, help="simulated seconds per whole run")
    parser.add_argument("--air", choices=["htb", "medium"], default="htb", help="the whole runs' air")
    parser.add_argument("--device", default="host", help="the fleet's companions' device profile")
    parser.add_argument("--probes", choices=["in-turn", "none"], default="in-turn", help="the fleet's probes")
    parser.add_argument("--latency-samples", type=int, default=40)
    parser.add_argument("--iperf-s", type=int, default=3)
    args = _common.parse_args(parser, SMOKE)
    if shutil.which("iperf3") is None:
        print("network_emulation: iperf3 is not installed", file=sys.stderr)
        return 2
    folder = _common.kernel_runs_folder("network_emulation", "nac-bench-net-")
    if folder is None:
        return 2
    try:
        for speedup in args.speedups:
            print(json.dumps({"delay_line": delay_line(speedup, args.latency_samples, args.iperf_s, folder)}),
                  flush=True)
        for rate in args.rates:
            print(json.dumps({"shaping_accuracy": shaping_accuracy(rate, args.iperf_s, folder)}), flush=True)
        print(json.dumps({"update_latency": update_latency(args.latency_samples, folder)}), flush=True)
        for vehicles in args.fleets:
            runs = {x: whole_run(vehicles, x, args.duration_s, folder, args.air, args.device, args.probes == "in-turn")
                    for x in args.speedups}
            for run in runs.values():
                print(json.dumps({"whole_run": run}), flush=True)
            base_x = args.speedups[0]  # each other speed-up's results against the first one's
            base = runs[base_x]
            for x, run in runs.items():
                if x != base_x and base["iterations_per_sim_min"] and run["iterations_per_sim_min"]:
                    print(json.dumps({"versus_first": {
                        "vehicles": vehicles, "air": args.air, "speedup": x, "first_speedup": base_x,
                        "iterations_per_sim_min_ratio": round(run["iterations_per_sim_min"] /
                                                              base["iterations_per_sim_min"], 3),
                        "by_window_ratio_95": _interval(base, run),
                        "throughput_ratio": round(run["mean_throughput_mbps"] / base["mean_throughput_mbps"], 3)
                        if base["mean_throughput_mbps"] and run["mean_throughput_mbps"] else None}}), flush=True)
            if not all(r["ok"] for r in runs.values()):
                return 1
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
