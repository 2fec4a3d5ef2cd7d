"""Real-time factor of the SITL for 1 to 500 vehicles, every vehicle streaming its default telemetry on both
links to a client that reads all of it.

The simulator runs as `nac-sitl run --speedup 1000` (as fast as it can) pinned to one core; the client runs in
this process pinned to the other core, receives every datagram, counts frames per message id and reads the
simulated clock from SYSTEM_TIME. Real-time factor = simulated seconds / wall seconds over the window.

One SITL holds at most 250 vehicles (a MAVLink system id is one byte, and each vehicle has its own): more are
split over several SITL processes, as a lab would run them, all pinned to the same core; their real-time factor
is the slowest one's.

    python benchmarks/sitl_scale.py [--vehicles 1 10 50 100 250 500] [--seconds 10] [--smoke]
"""

from __future__ import annotations

import argparse
import math
import os
import selectors
import socket
import struct
import sys
import time

from sitl.launcher import SitlProcess, allocate_base_port
from sitl.server import SitlConfig

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SYSTEM_TIME_ID = 2
VEHICLES_PER_SITL = 250
# --smoke: the same measurement, a few seconds in all; 5 vehicles over two SITL processes, as 500 are
SMOKE = {"vehicles": [1, 5], "seconds": 2.0, "warmup": 1.0, "per_sitl": 3}


def start_sitls(vehicles: int, per_sitl: int, sel: selectors.BaseSelector, sockets: list) -> list[SitlProcess]:
    """SITL processes for `vehicles`, at most per_sitl each, on core 0; their sockets registered in sel with the
    process index as data."""
    count = math.ceil(vehicles / per_sitl)
    procs = []
    for k in range(count):
        n = vehicles // count + (k < vehicles % count)
        base = allocate_base_port(n)
        for i in range(n):
            for slot in (0, 1):
                s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
                s.bind(("127.0.0.1", base + 10 * i + slot))
                s.setblocking(False)
                sel.register(s, selectors.EVENT_READ, k)
                sockets.append(s)
        proc = SitlProcess(SitlConfig(vehicles=n, speedup=1000.0, gcs_base_port=base, companion_base_port=base + 1,
                                      tcp_base_port=0))
        procs.append(proc)
        proc.start()
        os.sched_setaffinity(proc.proc.pid, {0})
    return procs


def measure(vehicles: int, seconds: float, warmup_s: float = 2.0, per_sitl: int = VEHICLES_PER_SITL) -> dict:
    sel = selectors.DefaultSelector()
    sockets: list[socket.socket] = []
    frames = 0
    bytes_in = 0
    procs: list[SitlProcess] = []
    try:
        procs = start_sitls(vehicles, per_sitl, sel, sockets)
        sim_ms: list[int | None] = [None] * len(procs)
        first = None
        start = time.monotonic()
        while time.monotonic() - start < warmup_s + seconds:
            for key, _ in sel.select(0.1):
                sock, k = key.fileobj, key.data
                while True:
                    try:
                        data = sock.recv(2048)
                    except BlockingIOError:
                        break
                    counting = time.monotonic() - start >= warmup_s
                    offset = 0
                    while offset + 12 <= len(data) and data[offset] == 0xFD:  # frames packed in a datagram
                        length = data[offset + 1]
                        msgid = data[offset + 7] | data[offset + 8] << 8 | data[offset + 9] << 16
                        if msgid == SYSTEM_TIME_ID and data[offset + 5] == 1:
                            payload = data[offset + 10:offset + 10 + length] + bytes(12)
                            sim_ms[k] = struct.unpack_from("<QI", payload)[1]
                        offset += 12 + length
                        if counting:
                            frames += 1
                    if counting:
                        if first is None and None not in sim_ms:
                            first = (time.monotonic(), list(sim_ms), frames)
                        bytes_in += len(data)
        end = (time.monotonic(), list(sim_ms), frames)
    finally:
        for proc in procs:
            proc.stop()
        for s in sockets:
            s.close()
    if first is None or end[0] <= first[0]:
        raise RuntimeError(f"{vehicles} vehicles: no SYSTEM_TIME from every SITL within {warmup_s + seconds:g} s")
    wall = end[0] - first[0]
    sim = min(b - a for a, b in zip(first[1], end[1], strict=True)) / 1000.0
    return {"vehicles": vehicles, "sitls": len(procs), "rtf": sim / wall, "frames_per_s": (end[2] - first[2]) / wall,
            "mbit_per_s": bytes_in * 8 / wall / 1e6}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, nargs="+", default=[1, 10, 50, 100, 250, 500])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--warmup", type=float, default=2.0, help="seconds before the window opens")
    parser.add_argument("--per-sitl", type=int, default=VEHICLES_PER_SITL, help="most vehicles in one SITL process")
    args = _common.parse_args(parser, SMOKE)
    os.sched_setaffinity(0, {1 % os.cpu_count()})
    print("| vehicles | SITL processes | real-time factor | frames/s read by the client | Mbit/s |")
    print("| ---: | ---: | ---: | ---: | ---: |")
    for n in args.vehicles:
        r = measure(n, args.seconds, args.warmup, args.per_sitl)
        print(f"| {r['vehicles']} | {r['sitls']} | {r['rtf']:.1f}x | {r['frames_per_s']:,.0f} | "
              f"{r['mbit_per_s']:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
