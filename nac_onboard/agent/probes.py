"""The master's probe schedule: every period, one throughput probe to each worker, logged with positions.

The workers are probed in turn (a round starts every period_s), or, with `concurrent`, each on a schedule of its
own at the same time as the others, as one iperf3 client per link would: a probe to a worker out of range that
waits out its timeouts then holds up no other worker's, and every link carries its probe traffic in the same
seconds.

A probe occupies a path for duration_s out of every period_s (the duty cycle), and rate_bps can cap it further,
so the compute traffic sharing the Wi-Fi is not starved. Each record is the iperf3-shaped result of
`throughput.probe` plus who probed whom, both positions at the start and end of the probe and their distances.
A probe that fails is logged too, with iperf3's `error` key: a broken link is a measurement, not a gap; its
`error_kind` says whose fault it was ("link": nothing more got through, kept in the analysis as a zero; "server":
the server refused or answered wrongly, left out). A probe that raises anything else (a bug, a target out of
range) is a `probe_failed` record, and the schedule goes on: no answer from any server stops later probes.
With `emulate_channel` (SITL), each probe is paced at the channel model's capacity for the pair's distance at
its start, and a pair beyond the model's range fails as a real one would: loopback then looks like the radio.
Periods and durations are in the run's time (nac_onboard.clock): at a speed-up X a probe lasts duration_s / X on
the wall clock and its bytes move X times faster, so the record keeps what the wire saw (iperf3's fields) and
adds `speedup` and `t_sim_s`: the rate in bits per simulated second is bits_per_second / speedup.
When the agent stops, `abort` ends the probes under way at once (their sockets shut, their iperf3 clients killed):
a probe cut short that way measured nothing and is a `probe_skipped` record, not a failed link.
"""

from __future__ import annotations

import logging
import math
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

from nac_onboard.agent.config import ThroughputSection
from nac_onboard.agent.snapshot import AgentSnapshot, ProbeResult, position
from nac_onboard.clock import Clock, slowed_s
from nac_onboard.flight_log import JsonlLog
from nac_onboard.link import iperf3
from nac_onboard.link.emulation import SleepEmulation
from nac_onboard.link.throughput import (
    ANSWER_MARGIN_S,
    GRACE_S,
    IDLE_TIMEOUT_S,
    LINK,
    MIN_INTERVAL_S,
    ProbeError,
    probe,
)
from nac_onboard.records import kinds

log = logging.getLogger(__name__)

# simulated seconds a probe waits for its connection (and, as throughput.GRACE_S and ANSWER_MARGIN_S, for its
# answer): at a speed-up X the wall-clock waits are X times shorter, so a worker out of range costs a sped-up run
# the same simulated time as a real-time one (wall-clock waits made a stalled probe hold its worker's schedule for
# 34 simulated seconds at 4x against 10 at 1x: a quarter as many failed probes, a higher mean throughput)
CONNECT_TIMEOUT_S = 3.0
IPERF3_END_S = 10.0  # after its test, iperf3's exchange of results: over a slowed air, the run's seconds below 1x
GO_POLL_S = 0.05  # wall: how often a schedule waiting for its start file looks for it


def received_bps(result: dict) -> float:
    """The receiver's rate in an iperf3-shaped result (ours or iperf3's); 0.0 for a probe that failed."""
    try:
        return float(result["end"]["sum_received"]["bits_per_second"])
    except (KeyError, TypeError, ValueError):
        return 0.0


class ProbeScheduler:
    def __init__(self, settings: ThroughputSection, self_id: str, targets: Callable[[], list[tuple[str, str, int]]],
                 snapshot: Callable[[], AgentSnapshot], out: JsonlLog, stop: threading.Event,
                 emulation: SleepEmulation | None = None, clock: Clock | None = None):
        self.settings, self.self_id = settings, self_id
        self.targets, self.snapshot = targets, snapshot  # [(id, host, port)] to probe; where everyone is now
        self.out, self.stop_event = out, stop
        self.rounds = 0
        self._listed: set[str] = set()  # concurrent: the targets of the last round (repr), each with a schedule
        self.latest: dict[str, tuple[float, float]] = {}  # peer -> (monotonic end, bits/s; 0: failed)
        self.emulation = emulation  # SITL: pace each probe at the channel model's rate for the pair's distance
        self.clock = clock or Clock()
        self._thread = threading.Thread(target=self._run, name="throughput-probes", daemon=True)
        self._under_way: set = set()  # the sockets and iperf3 processes of probes under way, for abort()
        self._cut: set = set()  # those abort() ended
        self._lock = threading.Lock()

    def start(self) -> ProbeScheduler:
        self._thread.start()
        return self

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)

    def abort(self) -> None:
        """End every probe under way now (set the stop event first: a probe that starts after this ends at once).
        Without it a probe ends by its own deadlines, seconds after the agent was told to stop."""
        with self._lock:
            under_way = list(self._under_way)
            self._cut.update(under_way)
        for item in under_way:
            _end(item)

    def _track(self, item) -> None:
        with self._lock:
            self._under_way.add(item)
            stopped = self.stop_event.is_set()
            if stopped:
                self._cut.add(item)
        if stopped:
            _end(item)

    def _untrack(self, item) -> bool:
        """Forget a probe's socket or process; whether abort() cut it short."""
        with self._lock:
            self._under_way.discard(item)
            cut = item in self._cut
            self._cut.discard(item)
        return cut

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def _run(self) -> None:
        """Rounds until stopped. No probe, target list or answer can end the schedule: an exception from one
        probe is logged as a probe_failed record and the round goes on to the next target. Concurrent: each
        round starts a schedule for every target that has none, and ends those of targets no longer listed."""
        if not self._wait_for_go():
            return
        next_round = time.monotonic()
        schedules: dict[str, threading.Thread] = {}
        while not self.stop_event.wait(max(next_round - time.monotonic(), 0.0)):
            next_round += self.clock.wall_s(self.settings.period_s)
            try:
                targets = list(self.targets())
            except Exception:
                log.exception("throughput probes: the target list failed; trying again next round")
                targets = []
            if self.settings.concurrent:
                self._listed = {repr(target) for target in targets}
                for target in targets:
                    key = repr(target)
                    if key not in schedules or not schedules[key].is_alive():
                        schedules[key] = threading.Thread(target=self._run_one, args=(target, key), daemon=True,
                                                          name=f"throughput-probes {key}"[:60])
                        schedules[key].start()
                targets = []
            for target in targets:
                if self.stop_event.is_set():
                    return
                self._probe_guarded(target)
            self.rounds += 1
            next_round = max(next_round, time.monotonic())
        # each schedule ends at its next wait; a probe under way ends by its own deadlines (connect 3 s, length,
        # the server's grace 5 s, the answer's margin 3 s)
        deadline = time.monotonic() + self.clock.wall_s(self.settings.duration_s) + 12.0
        for schedule in schedules.values():
            schedule.join(max(deadline - time.monotonic(), 0.0))

    def _wait_for_go(self) -> bool:
        """Until the start file exists (True), or the agent stops first (False)."""
        go = Path(self.settings.start_file)
        if not self.settings.start_file or go.exists():
            return True
        log.info("throughput probes: waiting for %s", go)
        while not go.exists():
            if self.stop_event.wait(GO_POLL_S):
                return False
        return True

    def _run_one(self, target, key: str) -> None:
        """One target's probes, one every period_s, until stopped or no longer listed."""
        next_probe = time.monotonic()
        while key in self._listed and not self.stop_event.wait(max(next_probe - time.monotonic(), 0.0)):
            next_probe = max(next_probe + self.clock.wall_s(self.settings.period_s), time.monotonic())
            self._probe_guarded(target)

    def _probe_guarded(self, target) -> None:
        try:
            peer_id, host, port = target
            self.probe_once(peer_id, host, port)
        except Exception as err:  # a bug, or input nobody checked: one probe lost, never the schedule
            log.exception("throughput probe to %r failed", target)
            given = list(target)[:3] if isinstance(target, (tuple, list)) else [target]
            peer_id, host, port = (given + [None, None, None])[:3]
            try:
                self.out.write(kinds.PROBE_FAILED, server=str(peer_id), host=str(host),
                               port=port if isinstance(port, int) and not isinstance(port, bool) else -1,
                               error=f"{type(err).__name__}: {err}"[:500])
            except Exception:
                log.exception("throughput probes: could not log the failed probe")

    def probe_once(self, peer_id: str, host: str, port: int) -> dict:
        s = self.settings
        before = self.snapshot()
        fields: dict = {"client": self.self_id, "server": peer_id, "host": host, "port": port,
                        "t_sim_s": self.clock.now_s(), "speedup": self.clock.speedup}
        distance_m = before.distance_m(self.self_id, peer_id)
        if self.emulation is not None and distance_m is None:
            # no distance, no emulated link: nothing was measured, so it is not a failed probe either
            return self.out.write(kinds.PROBE_SKIPPED, **fields, reason="no position for one of the pair yet")
        rate_bps = s.rate_bps or None
        wall = self.clock.wall_s
        started: list = []

        def track(item) -> None:
            started.append(item)
            self._track(item)
        try:
            if self.emulation is not None:
                rate_bps = self._emulated_rate_bps(peer_id, distance_m, rate_bps)
                fields["emulated_channel"] = self.emulation.channel.name
                fields["emulated_rate_bps"] = rate_bps
            if s.tool == "iperf3":
                seconds = max(1, math.ceil(wall(s.duration_s) - 1e-9))
                fields["duration_wall_s"] = seconds  # whole seconds: longer than duration_s when sped up
                result = iperf3.client_result(host, port, seconds, started=track,
                                              timeout_s=seconds + slowed_s(IPERF3_END_S, self.clock.speedup))
            else:
                result = probe(host, port, duration_s=None if s.bytes else wall(s.duration_s),
                               nbytes=s.bytes or None, interval_s=max(wall(s.interval_s), MIN_INTERVAL_S),
                               rate_bps=rate_bps * self.clock.speedup if rate_bps else None,
                               connect_timeout_s=wall(CONNECT_TIMEOUT_S), grace_s=wall(GRACE_S),
                               answer_margin_s=wall(ANSWER_MARGIN_S), started=track,
                               idle_timeout_s=slowed_s(IDLE_TIMEOUT_S, self.clock.speedup))
        except ProbeError as err:
            result = {"error": str(err), "error_kind": err.kind}
        except iperf3.Iperf3Error as err:
            result = {"error": str(err), "error_kind": LINK}
        finally:
            cut = any([self._untrack(item) for item in started])
        if cut and "error" in result:
            probe_fields = {f.name for f in kinds.PROBE_SKIPPED.fields}
            return self.out.write(kinds.PROBE_SKIPPED, **{k: v for k, v in fields.items() if k in probe_fields},
                                  reason="the agent stopped during the probe")
        after = self.snapshot()
        fields["positions"] = {"start": self._pair(before, peer_id), "end": self._pair(after, peer_id)}
        fields["distance_m"] = distance_m
        fields["distance_end_m"] = after.distance_m(self.self_id, peer_id)
        self.latest[peer_id] = (time.monotonic(), received_bps(result))
        return self.out.write(kinds.THROUGHPUT, **fields, **result)

    def results(self) -> tuple[ProbeResult, ...]:
        """Each peer's latest probe, for the state feed."""
        now = time.monotonic()
        latest = self.latest.copy()  # one step under the GIL: the probe thread may add a peer meanwhile
        return tuple(ProbeResult(peer, bps, now - t) for peer, (t, bps) in sorted(latest.items()))

    def _emulated_rate_bps(self, peer_id: str, distance_m: float, cap_bps: float | None) -> float:
        link = self.emulation.link(distance_m, peer_id, (self.self_id, peer_id))
        channel = self.emulation.channel
        if not link.in_range:
            # a real probe would wait out its connect timeout; the path is idle for the probe's slot either way
            self.stop_event.wait(self.clock.wall_s(self.settings.duration_s))
            raise ProbeError(f"out of range: {channel.name} gives {link.capacity_bps / 1e6:.3f} Mbit/s at "
                             f"{distance_m:.1f} m (minimum {channel.min_rate_bps / 1e6:g})")
        return min(link.capacity_bps, cap_bps) if cap_bps else link.capacity_bps

    def _pair(self, snapshot: AgentSnapshot, peer_id: str) -> dict:
        out = {}
        for who in (self.self_id, peer_id):
            vehicle = snapshot.vehicle(who)
            out[who] = None if vehicle is None else position(vehicle)
        return out


def _end(item) -> None:
    """A probe's socket shut (its waits return at once) or its iperf3 client killed."""
    try:
        if isinstance(item, socket.socket):
            item.shutdown(socket.SHUT_RDWR)
        elif isinstance(item, subprocess.Popen):
            item.kill()
    except OSError:
        pass  # already closed or exited: the probe is ending anyway
