"""CPU and memory of the onboard agent with 50 Hz telemetry in and its log at 10 Hz (target: < 5 % of one core,
< 80 MB RSS).

A one-vehicle SITL runs in real time, pinned to one core; the agent (`nac-onboard agent`, a child process pinned
to the other core) asks it for every stream at 50 Hz, logs telemetry at 10 Hz, writes the .tlog and publishes
its peer state. A ground station flies the vehicle through a mission meanwhile so mode and mission events occur.
CPU = (utime + stime) of the agent over the window / window; RSS = VmRSS at the end, VmHWM its peak.

    python benchmarks/agent_load.py [--seconds 60] [--stream-hz 50] [--telemetry-hz 10] [--smoke]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from missions.builder import waypoint_mission
from missions.model import MavCmd
from nac_onboard.child_process import AgentProcess
from nac_onboard.mavlink.client import VehicleClient
from nac_onboard.records import kinds
from sitl.launcher import SitlProcess, allocate_base_port
from sitl.server import SitlConfig

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SMOKE = {"seconds": 2.0, "settle": 1.0}  # --smoke: the same measurement over a short window


def run(seconds: float, stream_hz: float, telemetry_hz: float, settle_s: float = 3.0) -> dict:
    cores = sorted(os.sched_getaffinity(0))  # the SITL on the first, the agent on the last (the same on 1 core)
    base = allocate_base_port(1)
    config = SitlConfig(vehicles=1, speedup=1.0, gcs_base_port=base, companion_base_port=base + 1, tcp_base_port=0)
    with tempfile.TemporaryDirectory() as tmp, SitlProcess(config) as sitl:
        os.sched_setaffinity(sitl.pid, {cores[0]})
        agent_toml = _common.agent_config(
            Path(tmp), "bench", "worker", f"udpin:127.0.0.1:{base + 1}", autopilot={"stream_hz": stream_hz},
            log={"telemetry_hz": telemetry_hz, "tlog": True})
        with AgentProcess(agent_toml) as agent:
            os.sched_setaffinity(agent.pid, {cores[-1]})
            gcs = VehicleClient(f"udpin:127.0.0.1:{base}", sysid=1)
            gcs.wait_heartbeat(10.0)
            home = config.home
            legs = [(30, 0), (30, 30), (0, 30), (0, 0)] * 3
            accepted = gcs.upload(waypoint_mission(home.lat_deg, home.lon_deg, legs, alt_m=10.0))
            if accepted != 0:
                raise RuntimeError(f"mission upload refused: MISSION_ACK type {accepted}")
            gcs.command_ok(MavCmd.COMPONENT_ARM_DISARM, 1)
            gcs.command_ok(MavCmd.MISSION_START, 0, 0)
            time.sleep(settle_s)  # let the stream-rate request take effect before the window opens
            cpu0, t0 = _common.cpu_s(agent.pid), time.monotonic()
            end = t0 + seconds
            while time.monotonic() < end:
                gcs.poll(min(0.5, end - time.monotonic()))
            cpu1, t1 = _common.cpu_s(agent.pid), time.monotonic()
            memory = _common.memory_mb(agent.pid)
            gcs.close()
            agent.stop()
        log = [json.loads(line) for line in kinds.AGENT_LOG.at(Path(tmp) / "bench", "bench").read_text().splitlines()]
        stopped = log[-1]
        telemetry = [r for r in log if r["kind"] == kinds.TELEMETRY.name]
        frames_per_s = stopped["frames_in"] / (telemetry[-1]["t_s"] - log[0]["t_s"])
    return {"cpu_pct_of_one_core": 100 * (cpu1 - cpu0) / (t1 - t0), "rss_mb": memory["VmRSS"],
            "peak_rss_mb": memory["VmHWM"], "frames_in_per_s": frames_per_s,
            "telemetry_records_per_s": len(telemetry) / (telemetry[-1]["t_s"] - telemetry[0]["t_s"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--stream-hz", type=float, default=50.0)
    parser.add_argument("--telemetry-hz", type=float, default=10.0)
    parser.add_argument("--settle", type=float, default=3.0, help="seconds from arming to the window")
    args = _common.parse_args(parser, SMOKE)
    result = run(args.seconds, args.stream_hz, args.telemetry_hz, args.settle)
    print(f"agent over {args.seconds:g} s, streams at {args.stream_hz:g} Hz, log at {args.telemetry_hz:g} Hz:")
    print(f"  CPU {result['cpu_pct_of_one_core']:.2f} % of one core (target < 5 %)")
    print(f"  RSS {result['rss_mb']:.1f} MB, peak {result['peak_rss_mb']:.1f} MB (target < 80 MB)")
    print(f"  {result['frames_in_per_s']:.0f} MAVLink frames in per s, "
          f"{result['telemetry_records_per_s']:.1f} telemetry records per s")


if __name__ == "__main__":
    main()
