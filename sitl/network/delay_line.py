"""The air as a delay line (issue 28): one process holds every station's `air0`, a TUN device it creates in the
station's namespace, and carries each IP packet through the Wi-Fi medium (nac_onboard.radio.medium): queued at
its sender first in first out, sent when the medium gives that station the air, delivered (written to the
receiver's `air0`) when its frame has been on the air. These kernels have no netem; a TUN device is how a packet can
be held for a time. Everything a station sends (MPI, probes, peer state) goes through its one queue.

Time is the run's (nac_onboard.clock: simulated seconds, the simulator's pace): a frame of T simulated seconds is
written T / speed-up wall seconds after it was sent. What arrives late (the process could not keep up) is written
at once and counted, never dropped. What it cannot carry (not IPv4, to an address no station has, refused by the
receiver's air0) is counted too, each in its own counter, which the run's records and report carry.

    python -m sitl.network.delay_line NS:ADDRESS [NS:ADDRESS ...] [--queue-packets N] [--retry-limit N] [--seed N]

It prints `delay line ready` once every `air0` exists, then reads control lines on stdin, one JSON object a line:
first {"lead_s": L}, then link updates ({"phy_bps": [[...]], "per": [[...]], "fallback_bps": ..., "fallback_per":
...}, N x N each), and {"off": [k, ...]}: the stations whose radio is off now (a lost companion: its queue goes,
nothing reaches it). It prints its counters as one JSON object a line every STATS_PERIOD_S wall seconds and at its
end (stdin closed, or SIGTERM).

The lead: a packet's pass through the emulator costs wall time of its own (the sender's TUN write waking this
process, the write to the receiver's TUN waking the receiving process: on this 2-core VM 0.03-0.04 ms a pass with
the CPUs held awake, below), which the medium's time does not include. Until the lead arrives, every packet is
passed straight through (no medium, no hold), so whoever starts the line can time that pass (sitl.network.medium_air
does: an echo between two stations); from then on each delivery is written L wall seconds before its time, never
before its packet was read. A 100-byte echo at 1x took 1.14 times the medium's round trip without it, 1.00-1.04
with it (docs/benchmarks.md).
"""

from __future__ import annotations

import argparse
import ctypes
import fcntl
import json
import os
import select
import signal
import socket
import struct
import sys
import time

import numpy as np

from nac_onboard.clock import from_env
from nac_onboard.radio.medium import BROADCAST, DEFAULT_QUEUE_PACKETS, DEFAULT_RETRY_LIMIT, MacTiming, Medium
from sitl.network.netns import NetworkError, in_netns

TUNSETIFF, TUNSETOFFLOAD, IFF_TUN, IFF_NO_PI, IFF_VNET_HDR = 0x400454CA, 0x400454D0, 0x0001, 0x1000, 0x4000
TUN_F_CSUM, TUN_F_TSO4 = 0x01, 0x02
VNET_HDR = struct.Struct("<BBHHHH")  # virtio_net_hdr: flags, gso_type, hdr_len, gso_size, csum_start, csum_offset
VNET_GSO_NONE = 0
VNET_F_NEEDS_CSUM = 1  # the checksum is partial (the stack's offload): a receiving stack trusts it
TCP_FIN, TCP_PSH, TCP_CWR = 0x01, 0x08, 0x80
PR_SET_TIMERSLACK = 29
MAX_WAIT_S = 0.05  # wall: the longest select() sleeps, so stdin and the counters are served
# Wall seconds a timed wake-up is begun early and the rest spun on the clock; also how far ahead (times the pace)
# a transmission's start is decided, so a frame costs one wake-up (its delivery), not two. Measured on this VM with
# this process's scheduling (SCHED_FIFO, 1 us of timer slack, /dev/cpu_dma_latency at 0), 300 waits of 20 us to
# 1 ms each: select's wake-ups came 19-23 us late (median; 99th percentile 31-48 us) on an idle host, and 24-49 us
# (99th percentile 40-85 us) beside two CPU-bound loops, normal or idle class. The spin is most of this process's
# CPU at 4x (a frame's whole hold is shorter than it): with iperf3 through the air at 7,400 packets a second,
# 19.9 % of a core at 200 us, 11.9 % at 100 us, 8.0 % at 50 us, which a loaded host's wake-ups would outrun.
EARLY_S = 0.0001
STATS_PERIOD_S = 1.0
LATE_S = 0.001  # simulated: a delivery written this much after its time counts as late
MAX_LEAD_S = 0.005  # wall: no pass of a working host takes this long (a longer one measured is taken as this)
READY = "delay line ready"


def open_tun(namespace: str, name: str = "air0") -> int:
    """A TUN device named `name` in `namespace`, non-blocking; it exists while the fd is open, so it goes with
    this process however it ends. It takes TCP segmentation offload (as a virtio NIC does): the station's stack
    hands over up to 64 KB of a flow as one packet behind a virtio_net_hdr, and the medium charges it as the
    MTU-sized packets it stands for, so a bulk flow costs this process a few hundred reads a second, not
    thousands."""
    def make() -> int:
        fd = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
        fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", name.encode(), IFF_TUN | IFF_NO_PI | IFF_VNET_HDR))
        fcntl.ioctl(fd, TUNSETOFFLOAD, TUN_F_CSUM | TUN_F_TSO4)
        return fd
    return in_netns(namespace, make)


def segments_of(header: bytes, ip_bytes: int) -> int:
    """How many packets of the MTU a packet read with its virtio_net_hdr stands for (1 unless it is a TSO run)."""
    _, gso_type, hdr_len, gso_size, _, _ = VNET_HDR.unpack_from(header)
    if gso_type == VNET_GSO_NONE or gso_size == 0:
        return 1
    return max(1, -(-(ip_bytes - hdr_len) // gso_size))


def surviving_segments(packet: bytes, lost: tuple[int, ...]) -> list[bytes]:
    """A TCP segmentation offload run (read with its virtio_net_hdr) as the packets of its segments but the lost
    ones, each with its own virtio_net_hdr, as the sender's NIC would have cut them: IP total length and ID, TCP
    sequence number, FIN and PSH on the last segment only, CWR on the first only. Their checksums stay partial
    (NEEDS_CSUM: offset of the TCP header, its checksum field), as the run's was, which a receiving stack trusts."""
    v = VNET_HDR.size
    gso_size = VNET_HDR.unpack_from(packet)[3]
    ip = packet[v:]
    ihl = (ip[0] & 0x0F) * 4
    headers_len = ihl + (ip[ihl + 12] >> 4) * 4  # from the headers themselves: hdr_len is the stack's linear part
    headers, payload = ip[:headers_len], ip[headers_len:]
    ip_id, = struct.unpack_from("!H", ip, 4)
    seq, = struct.unpack_from("!I", ip, ihl + 4)
    flags = ip[ihl + 13]
    count = -(-len(payload) // gso_size)
    out = []
    for k in range(count):
        if k in lost:
            continue
        chunk = payload[k * gso_size:(k + 1) * gso_size]
        h = bytearray(headers)
        struct.pack_into("!HH", h, 2, headers_len + len(chunk), (ip_id + k) & 0xFFFF)
        struct.pack_into("!H", h, 10, 0)
        struct.pack_into("!H", h, 10, _ip_checksum(bytes(h[:ihl])))
        struct.pack_into("!I", h, ihl + 4, (seq + k * gso_size) & 0xFFFFFFFF)
        h[ihl + 13] = flags & ~((TCP_FIN | TCP_PSH) if k < count - 1 else 0) & ~(TCP_CWR if k else 0)
        out.append(VNET_HDR.pack(VNET_F_NEEDS_CSUM, VNET_GSO_NONE, headers_len, 0, ihl, 16) + bytes(h) + chunk)
    return out


def _ip_checksum(header: bytes) -> int:
    total = sum(struct.unpack(f"!{len(header) // 2}H", header))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


class DelayLine:
    def __init__(self, namespaces: list[str], addresses: list[str], queue_packets: int, retry_limit: int,
                 seed: int, out=None):
        self.clock = from_env()
        self.medium = Medium(len(namespaces), MacTiming(), queue_packets, retry_limit, seed)
        self.index = {socket.inet_aton(a): k for k, a in enumerate(addresses)}
        self.fds = [open_tun(ns) for ns in namespaces]
        self.out = sys.stdout if out is None else out  # the stdout of now, not of import time
        self.counters = {"packets_in": 0, "not_ipv4": 0, "unknown_destination": 0, "late": 0, "max_late_s": 0.0,
                         "updates": 0, "bad_updates": 0, "runs_cut": 0, "passed": 0, "write_failed": 0,
                         "flushed": 0}
        self.lead_s: float | None = None  # wall; None: not given yet, packets pass straight through
        self.links: dict[str, np.ndarray | None] | None = None  # as the last update gave them
        self.off: set[int] = set()  # stations whose radio is off (a lost companion): nothing reaches or leaves them
        self.queue_s: list[float] = []  # since the last counters line
        self.queue_by_station_s: list[list[float]] = [[] for _ in namespaces]  # the same, by the sending station
        self.air_s: list[float] = []
        self.late_s: list[float] = []  # how long after its time each delivery was written (simulated), the same
        self._stop = False
        self._cpu0_s, self._wall0_s = time.process_time(), time.monotonic()  # its own cost, in its counters

    def run(self, control) -> None:
        # select(2) sleeps to the microsecond; epoll and poll round a timeout up to whole milliseconds, which
        # would add a millisecond to every frame of a few hundred microseconds (measured: 2.9 ms round trips
        # against the model's 0.49). A station count of fds is well within select's limits. Bare, not through a
        # selectors.SelectSelector, whose bookkeeping costs 0.7 us a call more: at 4x a lone frame's whole hold
        # is some 40 us of wall time.
        _fine_timer_slack()
        station_of = {fd: k for k, fd in enumerate(self.fds)}
        control_fd = control.fileno()
        os.set_blocking(control_fd, False)
        watched = [*self.fds, control_fd]
        pending = b""
        next_stats = time.monotonic() + STATS_PERIOD_S
        print(READY, file=self.out, flush=True)
        while not self._stop:
            self._deliver()
            due = self.medium.next_event_s()  # simulated
            # from the clock read after the medium's work, so that work does not lengthen the hold
            now, speedup = self.clock.now_s(), self.clock.speedup
            wait = MAX_WAIT_S if due is None else min((due - now) / speedup - (self.lead_s or 0.0), MAX_WAIT_S)
            ready = select.select(watched, [], [], max(wait - EARLY_S, 0.0))[0]
            if not ready and due is not None:
                until_s = now + wait * speedup
                while self.clock.now_s() < until_s:
                    pass  # the last stretch spun on the clock: a timed wake-up comes late (EARLY_S)
            now = self._deliver()
            for fd in ready:
                if fd == control_fd:
                    chunk = os.read(control_fd, 1 << 20)
                    if not chunk:
                        self._stop = True
                        break
                    pending += chunk
                    *lines, pending = pending.split(b"\n")
                    for line in lines:
                        self._update(line)
                else:
                    self._take(station_of[fd], fd, now)
            if time.monotonic() >= next_stats:
                next_stats += STATS_PERIOD_S
                self._stats(now)
        self._stats(self.clock.now_s())

    def stop(self, *_) -> None:
        self._stop = True

    def _take(self, src: int, fd: int, now_s: float) -> None:
        while True:
            try:
                packet = os.read(fd, 65535)
            except (BlockingIOError, InterruptedError):
                return
            self.counters["packets_in"] += 1
            ip = VNET_HDR.size
            if len(packet) < ip + 20 or packet[ip] >> 4 != 4:
                self.counters["not_ipv4"] += 1  # IPv6 is off on air0; anything else is not for the air
                continue
            dst = self.index.get(packet[ip + 16:ip + 20])
            if dst is None:
                if packet[ip + 19] != 255:
                    self.counters["unknown_destination"] += 1
                    continue
                dst = BROADCAST
            size = len(packet) - ip
            if self.lead_s is None:
                self._pass(dst, src, packet)
                continue
            self.medium.offer(now_s, src, dst, size, packet, segments_of(packet, size))

    def _pass(self, dst: int, src: int, packet: bytes) -> None:
        """Before the lead is given: the packet at once to its destination (every other station, if broadcast)."""
        self.counters["passed"] += 1
        for k in (range(len(self.fds)) if dst == BROADCAST else (dst,)):
            if k != src:
                self._write(k, packet)

    def _deliver(self) -> float:
        now = self.clock.now_s()
        speedup = self.clock.speedup
        lead_s = (self.lead_s or 0.0) * speedup  # simulated
        for delivery in self.medium.run_until(now + lead_s, EARLY_S * speedup):
            late = now + lead_s - delivery.delivered_s
            self.late_s.append(late)
            if late > LATE_S:
                self.counters["late"] += 1
                self.counters["max_late_s"] = max(self.counters["max_late_s"], late)
            self.queue_s.append(delivery.queue_s)
            self.queue_by_station_s[delivery.frame.src].append(delivery.queue_s)
            self.air_s.append(delivery.delivered_s - delivery.frame.first_sent_s)
            packets = [delivery.frame.item]
            if delivery.lost_segments:
                packets = surviving_segments(delivery.frame.item, delivery.lost_segments)
                self.counters["runs_cut"] += 1
            for packet in packets:
                self._write(delivery.dst, packet)
        return now

    def _write(self, dst: int, packet: bytes) -> None:
        try:
            os.write(self.fds[dst], packet)
        except OSError:  # the receiver's air0 is down or its queue full: the packet is lost there
            self.counters["write_failed"] += 1

    def _update(self, line: bytes) -> None:
        n = len(self.fds)
        try:
            update = json.loads(line)
            if isinstance(update, dict) and "lead_s" in update:
                self._set_lead(update["lead_s"])
                return
            if isinstance(update, dict) and "off" in update:
                self._set_off(update["off"])
                return
            matrices = {key: np.asarray(update[key], float) for key in ("phy_bps", "per")}
            for key in ("fallback_bps", "fallback_per"):
                matrices[key] = np.asarray(update[key], float) if key in update else None
            if any(m is not None and (m.shape != (n, n) or not np.isfinite(m).all()) for m in matrices.values()):
                raise ValueError(f"every matrix {n} x {n} and finite")
        except (ValueError, KeyError, TypeError) as err:
            self.counters["bad_updates"] += 1
            print(json.dumps({"error": f"link update refused: {err}"}), file=self.out, flush=True)
            return
        self.links = matrices
        self._give_links()
        self.counters["updates"] += 1

    def _give_links(self) -> None:
        """The last update's links to the medium, with every station that is off out of everyone's range: a frame
        to it is tried to the retry limit and lost, as no acknowledgement comes from a radio without power."""
        if self.links is None:
            return
        rates = {key: self.links[key] for key in ("phy_bps", "fallback_bps")}
        if self.off:
            off = sorted(self.off)
            for key, m in rates.items():
                if m is not None:
                    m = m.copy()
                    m[off, :] = 0.0
                    m[:, off] = 0.0
                    rates[key] = m
        self.medium.set_links(rates["phy_bps"], self.links["per"], rates["fallback_bps"], self.links["fallback_per"])

    def _set_off(self, off) -> None:
        n = len(self.fds)
        if not isinstance(off, list) or not all(isinstance(k, int) and not isinstance(k, bool) and 0 <= k < n
                                                for k in off):
            raise ValueError(f"off: expected a list of station indices in 0..{n - 1}, got {off!r}")
        for k in set(off) - self.off:  # its queue goes with its power
            self.counters["flushed"] += self.medium.flush(k)
        self.off = set(off)
        self._give_links()

    def _set_lead(self, lead_s) -> None:
        if isinstance(lead_s, bool) or not isinstance(lead_s, int | float) or not 0 <= lead_s <= MAX_LEAD_S:
            raise ValueError(f"lead_s: expected wall seconds in 0..{MAX_LEAD_S:g}, got {lead_s!r}")
        self.lead_s = float(lead_s)

    def _stats(self, now_s: float) -> None:
        s = self.medium.stats
        line = {"t_sim_s": round(now_s, 4), **self.counters, "offered": s.offered, "delivered": s.delivered,
                "segments_delivered": s.segments_delivered,
                "queue_drops": s.queue_drops, "retry_drops": s.retry_drops, "exchanges": s.exchanges,
                "collisions": s.collisions, "busy_s": round(s.busy_s, 6),
                "backlog": [self.medium.backlog(k) for k in range(len(self.fds))],
                "queue_p50_s": _median(self.queue_s), "air_p50_s": _median(self.air_s),
                "late_p50_s": _median(self.late_s),
                "queue_p50_by_station_s": [_median(q) for q in self.queue_by_station_s],
                "cpu_s": round(time.process_time() - self._cpu0_s, 3),
                "wall_s": round(time.monotonic() - self._wall0_s, 3)}
        if self.lead_s is not None:
            line["lead_s"] = self.lead_s
        if self.off:
            line["stations_off"] = sorted(self.off)
        self.queue_s, self.air_s, self.late_s = [], [], []
        self.queue_by_station_s = [[] for _ in self.fds]
        print(json.dumps(line), file=self.out, flush=True)


def _hold_cpus_awake():
    """Idle CPUs poll instead of halting while this process lives: 0 written to /dev/cpu_dma_latency, held open
    (Linux PM QoS, Documentation/power/pm_qos_interface.rst; as cyclictest does). On a VM a halted vCPU takes 50-150
    us to wake (an IPI through the hypervisor), and every packet through the air wakes two processes: measured on
    this VM, a zero-hold echo through two TUN passes took 0.10-0.32 ms, 0.05 ms with this held. A polling idle CPU
    leaves it for any task at once. None: not allowed here (the waits are then the host's)."""
    try:
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
        os.write(fd, struct.pack("i", 0))
        return fd
    except OSError:
        return None


def _fine_timer_slack() -> None:
    """1 us of timer slack (PR_SET_TIMERSLACK) instead of Linux's default 50 us, for this process's waits."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_TIMERSLACK, 1000, 0, 0, 0)
    except (OSError, AttributeError):
        pass


DELAY_LINE_FIFO_PRIORITY = 1  # SCHED_FIFO's lowest: the air is the clock every station's traffic runs on, so
# it runs the moment a frame is due. At nice -10 it waited on the run queue for 4.6 s of a 41 s run of
# paper-flight-static at 4x (95 us a wake-up on average) and 14-24 % of its deliveries were late; at nice -20 12 %;
# at SCHED_FIFO 0.1 s and 2.4-2.8 % (docs/benchmarks.md). It sleeps in select() between frames, and Linux's
# real-time throttling (sched_rt_runtime_us, 95 % of each second by default) keeps a CPU for the host whatever it
# does. The last stretch of a wait spun on the clock is bounded by EARLY_S.
DELAY_LINE_NICE = -10  # without the right to SCHED_FIFO: before the stations' processes (weight 9,548 against
# 1,024 at nice 0)


def _before_the_stations() -> None:
    """The delay line's scheduling: SCHED_FIFO, else nice -10, else the stations' own (lateness is counted)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(DELAY_LINE_FIFO_PRIORITY))
        return
    except (OSError, AttributeError):
        pass
    try:
        os.setpriority(os.PRIO_PROCESS, 0, DELAY_LINE_NICE)
    except OSError:
        pass


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 6) if values else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sitl.network.delay_line", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("stations", nargs="+", help="NAMESPACE:ADDRESS of each station, in index order")
    parser.add_argument("--queue-packets", type=int, default=DEFAULT_QUEUE_PACKETS)
    parser.add_argument("--retry-limit", type=int, default=DEFAULT_RETRY_LIMIT)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    pairs = [s.rpartition(":") for s in args.stations]
    try:
        line = DelayLine([p[0] for p in pairs], [p[2] for p in pairs], args.queue_packets, args.retry_limit,
                         args.seed)
    except (NetworkError, OSError, ValueError) as err:
        print(f"delay line: {err}", file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, line.stop)
    signal.signal(signal.SIGINT, line.stop)
    _before_the_stations()
    line.counters["cpus_held_awake"] = _hold_cpus_awake() is not None  # the fd closes with the process
    line.run(sys.stdin)
    return 0


if __name__ == "__main__":
    sys.exit(main())
