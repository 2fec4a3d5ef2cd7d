"""CPU and memory of the onboard agent under a flood from the network (target: < 10 % of one core, memory flat):
forged peer state (valid JSON, unsigned or signed with the wrong key, with ever new ids) to its peer port, and
garbage to a routing endpoint from a sender that is not the configured tool, together at --rate datagrams/s.

The agent (`nac-onboard agent`, a child process pinned to one core) has a fleet key and a udpin routing endpoint
whose tool has already spoken; the flood comes from this process on the other core, paced in 10 ms batches.
CPU = (utime + stime) of the agent over the window / window; memory = VmRSS at the start, middle and end of the
window. At the end the agent's own counters say what it refused.

    python benchmarks/agent_flood.py [--seconds 30] [--rate 10000] [--smoke]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import tempfile
import time
from pathlib import Path

from nac_onboard.agent.peers import FleetKey, PeerState, encode_peer_state
from nac_onboard.child_process import AgentProcess
from nac_onboard.records import kinds
from sitl.launcher import free_port

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SMOKE = {"seconds": 2.0, "rate": 2000.0}  # --smoke: the same flood, briefly and thinner
BATCH_S = 0.01


def agent_config(tmp: Path, peer_port: int, routing_port: int) -> Path:
    return _common.agent_config(tmp, "flooded", "master", f"udpin:127.0.0.1:{free_port()}",
                                routing={"endpoints": [f"udpin:127.0.0.1:{routing_port}"]},
                                peers={"listen": f"127.0.0.1:{peer_port}"})


def flood(peer: tuple, routing: tuple, rate: float, seconds: float, pid: int) -> tuple[int, list[float]]:
    """Send for seconds at rate (half peer state, half routing garbage); RSS (MB) sampled at 0, 1/2 and the end."""
    wrong_key = FleetKey("fleet", b"w" * 32)
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    garbage = bytes(range(256)) * 2
    sent, rss = 0, [_common.memory_mb(pid)["VmRSS"]]
    t0 = time.monotonic()
    per_batch = max(int(rate * BATCH_S), 2)
    halfway = False
    try:
        while (now := time.monotonic()) - t0 < seconds:
            for k in range(per_batch // 2):
                state = PeerState(f"forged{sent + k}", "worker", time.time(), lat_deg=47.0, lon_deg=8.0, alt_m=500.0)
                sender.sendto(encode_peer_state(state, wrong_key if k % 2 else None), peer)
                sender.sendto(garbage, routing)
            sent += per_batch
            if not halfway and now - t0 >= seconds / 2:
                rss.append(_common.memory_mb(pid)["VmRSS"])
                halfway = True
            time.sleep(max(t0 + sent / rate - time.monotonic(), 0.0))
    finally:
        sender.close()
    rss.append(_common.memory_mb(pid)["VmRSS"])
    return sent, rss


def run(seconds: float, rate: float) -> dict:
    cores = sorted(os.sched_getaffinity(0))
    peer_port, routing_port = free_port(), free_port()
    with tempfile.TemporaryDirectory() as tmp:
        with AgentProcess(agent_config(Path(tmp), peer_port, routing_port)) as agent:
            os.sched_setaffinity(agent.pid, {cores[-1]})
            os.sched_setaffinity(0, {cores[0]})
            tool = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the configured tool speaks first
            tool.sendto(b"\xfd\x09\x00\x00\x00\xff\xbe\x00\x00\x00" + bytes(11), ("127.0.0.1", routing_port))
            cpu0, t0 = _common.cpu_s(agent.pid), time.monotonic()
            sent, rss = flood(("127.0.0.1", peer_port), ("127.0.0.1", routing_port), rate, seconds, agent.pid)
            cpu1, t1 = _common.cpu_s(agent.pid), time.monotonic()
            tool.close()
            agent.stop()
        stopped = json.loads(kinds.AGENT_LOG.at(Path(tmp) / "bench", "flooded").read_text().splitlines()[-1])
    return {"cpu_pct_of_one_core": 100 * (cpu1 - cpu0) / (t1 - t0), "rss_mb": rss, "sent": sent,
            "rate": sent / (t1 - t0), "peer_rejects": stopped.get("peer_rejects", {}),
            "routing_refused": stopped.get("routing_refused", 0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--rate", type=float, default=10000.0, help="datagrams per second, both floods together")
    args = _common.parse_args(parser, SMOKE)
    result = run(args.seconds, args.rate)
    print(f"agent under {result['rate']:,.0f} hostile datagrams/s for {args.seconds:g} s ({result['sent']:,} sent):")
    print(f"  CPU {result['cpu_pct_of_one_core']:.2f} % of one core (target < 10 %)")
    print("  RSS " + " / ".join(f"{mb:.1f}" for mb in result["rss_mb"]) + " MB at start / middle / end (flat)")
    print(f"  refused peer state by reason: {result['peer_rejects']}; routing frames refused: "
          f"{result['routing_refused']:,}")


if __name__ == "__main__":
    main()
