"""CPU and memory of the onboard agent under a flood from the network (target: < 10 % of one core, memory flat):
forged peer state (valid JSON, unsigned or signed with the wrong key, with ever new ids) to its peer port, and
garbage to a routing endpoint from a sender that is not the configured tool, together at --rate datagrams/s.

The agent (`nac-onboard agent`, a child process pinned to one core) has a fleet key and a udpin routing endpoint
whose tool has already spoken; the flood comes from this process on the other core, paced in 10 ms batches.
CPU = (utime + stime) of the agent over the window / window; memory = VmRSS at the start, middle and end of the
window. At the end the agent's own counters say what it refused.

    python benchmarks/agent_flood.py [--seconds 30] [--rate 10000] [--smoke]

--target autopilot floods the agent's autopilot link instead (--target both, the default, runs the two in turn;
issue 34: its udpin: once took every sender as the autopilot and answered them all): a real SITL (in this process)
is the autopilot and has spoken, then one-byte datagrams from --ports source ports on 127.0.0.1 and 127.0.0.2,
round robin, at --rate. Reported besides CPU and memory: the agent's telemetry records per second during the
flood (log.telemetry_hz = 10: 10 means untouched), whether they all hold the SITL's truth, and what it refused
(agent_stopped.autopilot_refused). Target: CPU < 10 % of one core at 10,000/s from 5,000 ports.

    python benchmarks/agent_flood.py --target autopilot [--seconds 10] [--rate 10000] [--ports 5000] [--smoke]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import socket
import tempfile
import time
from pathlib import Path

from nac_onboard.agent.peers import FleetKey, PeerState, encode_peer_state
from nac_onboard.child_process import AgentProcess
from nac_onboard.records import kinds
from sitl.launcher import free_port

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SMOKE = {"seconds": 2.0, "rate": 2000.0, "ports": 200}  # --smoke: the same flood, briefly and thinner
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


def autopilot_flood(port: int, rate: float, seconds: float, ports: int, pid: int) -> tuple[int, list[float]]:
    """One-byte datagrams to the autopilot link from `ports` sockets in turn, paced in BATCH_S batches."""
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, ports + 256), hard))
    senders = []
    try:
        for k in range(ports):
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            senders.append(sock)
            sock.bind(("127.0.0.1" if k % 2 else "127.0.0.2", 0))
        target = ("127.0.0.1", port)
        sent, rss = 0, [_common.memory_mb(pid)["VmRSS"]]
        per_batch = max(int(rate * BATCH_S), 1)
        t0, halfway = time.monotonic(), False
        while (now := time.monotonic()) - t0 < seconds:
            for k in range(sent, sent + per_batch):
                senders[k % ports].sendto(b"\x00", target)
            sent += per_batch
            if not halfway and now - t0 >= seconds / 2:
                rss.append(_common.memory_mb(pid)["VmRSS"])
                halfway = True
            time.sleep(max(t0 + sent / rate - time.monotonic(), 0.0))
        rss.append(_common.memory_mb(pid)["VmRSS"])
        return sent, rss
    finally:
        for sock in senders:
            sock.close()


def run_autopilot(seconds: float, rate: float, ports: int) -> dict:
    from nac_onboard.flight_log import read_jsonl
    from sitl.server import Sitl, SitlConfig

    cores = sorted(os.sched_getaffinity(0))
    companion = free_port()
    sim = Sitl(SitlConfig(vehicles=1, speedup=1.0, gcs_base_port=free_port(), companion_base_port=companion,
                          tcp_base_port=0)).start()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            config = _common.agent_config(Path(tmp), "flooded", "worker", f"udpin:127.0.0.1:{companion}")
            log_path = kinds.AGENT_LOG.at(Path(tmp) / "bench", "flooded")
            with AgentProcess(config) as agent:
                os.sched_setaffinity(agent.pid, {cores[-1]})
                os.sched_setaffinity(0, {cores[0]})
                deadline = time.monotonic() + 10.0
                while not (log_path.exists() and f'"{kinds.TELEMETRY.name}"' in log_path.read_text()):
                    if time.monotonic() > deadline:
                        raise SystemExit("the agent did not log telemetry from the SITL within 10 s")
                    time.sleep(0.05)
                cpu0, t0, wall0 = _common.cpu_s(agent.pid), time.monotonic(), time.time()
                sent, rss = autopilot_flood(companion, rate, seconds, ports, agent.pid)
                cpu1, t1, wall1 = _common.cpu_s(agent.pid), time.monotonic(), time.time()
                agent.stop()
            records = read_jsonl(log_path).records
            telemetry = [r for r in records if r["kind"] == kinds.TELEMETRY.name and wall0 <= r["t_s"] <= wall1]
            stopped = records[-1]
    finally:
        sim.stop()
    truth = sim.truth(0)
    believed = all(abs(r["lat_deg"] - truth["lat_deg"]) < 0.01 and not r["armed"] for r in telemetry)
    return {"cpu_pct_of_one_core": 100 * (cpu1 - cpu0) / (t1 - t0), "rss_mb": rss, "sent": sent,
            "rate": sent / (t1 - t0), "telemetry_per_s": len(telemetry) / (wall1 - wall0),
            "autopilot_refused": stopped.get("autopilot_refused", 0), "telemetry_is_truth": believed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--rate", type=float, default=10000.0, help="datagrams per second, both floods together")
    parser.add_argument("--target", choices=("peers", "autopilot", "both"), default="both",
                        help="peers: the peer port and a routing endpoint; autopilot: the autopilot link; both: "
                             "one after the other")
    parser.add_argument("--ports", type=int, default=5000, help="--target autopilot: source ports of the flood")
    args = _common.parse_args(parser, SMOKE)
    if args.target in ("peers", "both"):
        run_peers(args)
    if args.target in ("autopilot", "both"):
        result = run_autopilot(args.seconds, args.rate, args.ports)
        print(f"agent's autopilot link under {result['rate']:,.0f} one-byte datagrams/s from {args.ports:,} source "
              f"ports for {args.seconds:g} s ({result['sent']:,} sent):")
        print(f"  CPU {result['cpu_pct_of_one_core']:.2f} % of one core (target < 10 %)")
        print("  RSS " + " / ".join(f"{mb:.1f}" for mb in result["rss_mb"]) + " MB at start / middle / end (flat)")
        print(f"  telemetry records {result['telemetry_per_s']:.1f}/s (log.telemetry_hz 10), all the SITL's truth: "
              f"{result['telemetry_is_truth']}; refused {result['autopilot_refused']:,}")


def run_peers(args: argparse.Namespace) -> None:
    result = run(args.seconds, args.rate)
    print(f"agent under {result['rate']:,.0f} hostile datagrams/s for {args.seconds:g} s ({result['sent']:,} sent):")
    print(f"  CPU {result['cpu_pct_of_one_core']:.2f} % of one core (target < 10 %)")
    print("  RSS " + " / ".join(f"{mb:.1f}" for mb in result["rss_mb"]) + " MB at start / middle / end (flat)")
    print(f"  refused peer state by reason: {result['peer_rejects']}; routing frames refused: "
          f"{result['routing_refused']:,}")


if __name__ == "__main__":
    main()
