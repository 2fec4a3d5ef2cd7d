"""The kernel network with a frame-level air (`[network] air = "medium"`, issue 28): each station's namespace has
an `air0` that is a TUN device of one delay-line process (sitl.network.delay_line), which carries every packet
through the 802.11 medium model: one FIFO transmit queue per station, channel access, aggregation, retries and
collisions, in the run's simulated time. No bridge, no tc, no nftables: rate, loss, queueing and air time are the
medium's. The shaper hands it each pair's PHY rate and frame error rate (and the retry chain's fallback) instead of
HTB rates and drop rules; the delay line's counters become `air_medium` records in network.jsonl.

Before the medium takes the packets, the delay line passes them straight through while this times a small UDP echo
between two stations: half its median round trip is the host's own cost of a pass through the emulator, which the
delay line then takes off each delivery's hold (its `lead_s`).
"""

from __future__ import annotations

import json
import logging
import os
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from nac_onboard.child_process import die_with_parent_preexec
from nac_onboard.clock import ENV as CLOCK_ENV
from nac_onboard.flight_log import JsonlLog
from nac_onboard.radio.medium import DEFAULT_QUEUE_PACKETS, DEFAULT_RETRY_LIMIT
from nac_onboard.records import kinds
from sitl.network import netns
from sitl.network.air import AIR_PREFIX_LENGTH, AirNetwork, Station, end_fed_process, quick_acks
from sitl.network.delay_line import MAX_LEAD_S, READY
from sitl.network.shaping import AirState

log = logging.getLogger(__name__)
READY_TIMEOUT_S = 10.0
LEAD_ECHOES = 40  # round trips timed for the lead (after LEAD_WARMUP not counted): under 0.1 s in all
LEAD_WARMUP = 5
LEAD_GAP_S = 0.001  # between them. A pass costs more the longer the host was idle before it (measured on this VM,
# the CPUs held awake: 0.036, 0.058 and 0.108 ms at 1, 5 and 20 ms apart): timed on a busy air, the lead is the
# least a pass costs, so no delivery is written before its receiver could have had it from the medium
LEAD_ECHO_TIMEOUT_S = 1.0
LATE_WARN_SHARE = 0.05  # a second with this share of its deliveries written late is logged: the host fell behind
WARN_EVERY_S = 30.0  # wall: the least time between two such log lines (the records count every packet)


class MediumAir(AirNetwork):
    def __init__(self, vehicle_ids: list[str], ap: int | None, sharing: bool,
                 probe_ports: list[int | None] | None = None, speedup: float = 1.0,
                 queue_packets: int = DEFAULT_QUEUE_PACKETS, clock_path: Path | None = None, seed: int = 0,
                 congestion_control: str = "host", retry_limit: int = DEFAULT_RETRY_LIMIT):
        super().__init__(vehicle_ids, ap, sharing, probe_ports, speedup, congestion_control)
        self.queue_packets, self.clock_path, self.seed = queue_packets, clock_path, seed
        self.retry_limit = retry_limit  # the radio's: the sleep and htb networks' loss counts the same tries
        self.line: subprocess.Popen | None = None
        self.counters: dict | None = None  # the delay line's last counters
        self.errors: list[str] = []
        self._records: JsonlLog | None = None
        self._reader: threading.Thread | None = None
        self.lead_s = 0.0  # wall: the host's own cost of a pass, taken off each delivery's hold
        self._quiet_until = 0.0  # monotonic: no warning before it (WARN_EVERY_S)
        self._off: set[int] = set()  # stations silenced (a lost companion)

    @property
    def namespaces(self) -> list[str]:
        return [s.netns for s in self.stations]

    def record_to(self, out: JsonlLog) -> None:
        """From now on each counters line of the delay line is an `air_medium` record in `out`."""
        self._records = out

    def _build(self) -> None:
        self._add_namespaces()
        for s in self.stations:
            netns.run(["ip", "-n", s.netns, "link", "set", "lo", "up"], f"{s.vehicle_id}'s loopback")
            netns.run(["ip", "netns", "exec", s.netns, "sysctl", "-q", "-w", "net.ipv6.conf.all.disable_ipv6=1",
                       "net.ipv6.conf.default.disable_ipv6=1", *self.tcp_settings()], f"{s.vehicle_id}'s settings")
        env = {**os.environ, CLOCK_ENV: str(self.clock_path)} if self.clock_path is not None else None
        self.line = subprocess.Popen(
            [sys.executable, "-m", "sitl.network.delay_line", *(f"{s.netns}:{s.address}" for s in self.stations),
             "--queue-packets", str(self.queue_packets), "--retry-limit", str(self.retry_limit), "--seed",
             str(self.seed)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, bufsize=1, env=env,
            preexec_fn=die_with_parent_preexec())
        self._wait_ready()
        for s in self.stations:
            netns.run(["ip", "-n", s.netns, "-batch", "-"], f"{s.vehicle_id}'s air0",
                      f"addr add {s.address}/{AIR_PREFIX_LENGTH} dev air0\nlink set air0 up\n{quick_acks(s)}")
        self._reader = threading.Thread(target=self._read_counters, name="delay-line", daemon=True)
        self._reader.start()
        self.wait_for_carrier()
        self.lead_s = self._time_a_pass() if len(self.stations) > 1 else 0.0
        log.info("the host's pass through the delay line: %.3f ms (taken off each delivery)", self.lead_s * 1e3)
        self._send({"lead_s": self.lead_s})

    def _time_a_pass(self) -> float:
        """Half the median round trip of a 100-byte UDP echo between the first two stations while the delay line
        passes packets straight through (wall seconds). Its server is a thread of its own, as each station's receiver
        is a process of its own: waking a task that has waited costs more than waking the one that has just sent
        (with both ends in one thread the lead was 22-29 us and a 1x echo through the medium 1.03-1.07 times the
        model; with the server a thread, 32-38 us and 1.02-1.05: six runs each, in turn, 2026-11-29)."""
        a, b = self.stations[0], self.stations[1]
        try:
            round_trips = netns.udp_echo_round_trips(a.netns, b.netns, b.address, LEAD_WARMUP + LEAD_ECHOES,
                                                     LEAD_GAP_S, LEAD_ECHO_TIMEOUT_S, server_thread=True)
        except OSError as err:
            raise netns.NetworkError(f"the delay line did not pass an echo between {a.vehicle_id} and "
                                     f"{b.vehicle_id} within {LEAD_ECHO_TIMEOUT_S:g} s: {err}") from None
        return min(statistics.median(round_trips[LEAD_WARMUP:]) / 2, MAX_LEAD_S)

    def _wait_ready(self) -> None:
        seen: list[str] = []

        def first_line() -> None:
            seen.append(self.line.stdout.readline())

        reader = threading.Thread(target=first_line, daemon=True)
        reader.start()
        reader.join(READY_TIMEOUT_S)
        if not seen or seen[0].strip() != READY:
            self.line.kill()
            why = self.line.stderr.read() if self.line.poll() is not None else "no answer"
            raise netns.NetworkError(f"the delay line did not start within {READY_TIMEOUT_S:g} s: "
                                     f"{(seen[0] if seen else '').strip() or why.strip()}")

    def _read_counters(self) -> None:
        fields = {f.name for f in kinds.AIR_MEDIUM.fields}
        for line in self.line.stdout:
            try:
                counters = json.loads(line)
            except ValueError:
                continue
            if "error" in counters:
                self.errors.append(counters["error"])
                log.warning("delay line: %s", counters["error"])
                continue
            self._warn_of(counters)
            self.counters = counters
            if self._records is not None:
                self._records.write(kinds.AIR_MEDIUM, stations=[s.vehicle_id for s in self.stations],
                                    **{k: v for k, v in counters.items() if k in fields})

    def _warn_of(self, counters: dict) -> None:
        """A log line when, since the delay line's last counters, the host lost packets the medium had delivered
        (their receiver's air0 refused them) or fell behind (over LATE_WARN_SHARE of the deliveries late); at most
        one every WARN_EVERY_S, as the records and the report count every packet."""
        if time.monotonic() < self._quiet_until:
            return
        before = self.counters or {}
        lost = counters.get("write_failed", 0) - before.get("write_failed", 0)
        delivered = counters.get("delivered", 0) - before.get("delivered", 0)
        late = counters.get("late", 0) - before.get("late", 0)
        if lost > 0:
            log.warning("the air: %d packets the medium delivered were refused by their receivers' air0 (lost on this "
                        "host, not by the medium), %d in all", lost, counters["write_failed"])
        behind = delivered > 0 and late > LATE_WARN_SHARE * delivered
        if behind:
            log.warning("the air fell behind: %d of %d deliveries were written over 1 ms late (the latest so far "
                        "%.1f ms); the report counts them", late, delivered, counters.get("max_late_s", 0.0) * 1e3)
        if lost > 0 or behind:
            self._quiet_until = time.monotonic() + WARN_EVERY_S

    def silence(self, index: int, silent: bool = True) -> None:
        """As the htb air's, and the medium told: a station without power neither sends (its queue goes) nor
        acknowledges, so what is sent to it is tried to the retry limit and lost, as on the air."""
        if silent:
            self._off.add(index)
            self._send({"off": sorted(self._off)})
        super().silence(index, silent)
        if not silent:
            self._off.discard(index)
            self._send({"off": sorted(self._off)})

    @staticmethod
    def _running(station: Station) -> bool:
        """A TUN device with its reader attached is up with operstate UNKNOWN (it has no carrier of its own)."""
        shown = netns.run(["ip", "-n", station.netns, "-j", "link", "show", "dev", "air0"],
                          f"{station.vehicle_id}'s air0")
        try:
            flags = json.loads(shown)[0].get("flags", [])
        except (ValueError, IndexError, AttributeError):
            return False
        return "UP" in flags and "LOWER_UP" in flags

    def apply(self, state: AirState, pace: float) -> None:
        self._send({key: value.tolist() for key, value in state.frames.items()})

    def _send(self, control: dict) -> None:
        try:
            self.line.stdin.write(json.dumps(control) + "\n")
            self.line.stdin.flush()
        except (OSError, ValueError) as err:
            raise netns.NetworkError(f"the delay line stopped: {err}") from None

    def close(self) -> None:
        if self.line is not None:
            end_fed_process(self.line)  # its last counters, then its end: the TUN devices go with it
            if self._reader is not None:
                self._reader.join(2.0)
            self.line = None
        super().close()  # the namespaces
