"""The onboard agent: the companion computer's daemon (`nac-onboard agent --config FILE`, a systemd service).

One select loop owns the autopilot link, the routing endpoints, the peer socket and the local state feed; the
throughput server and the master's probes run in threads because a probe blocks for its whole duration.
Everything it observes goes to the run directory `LOG_DIR/RUN_ID/VEHICLE_ID/`:
  agent.jsonl       telemetry at log.telemetry_hz and events (link, mode, mission, peers)
  throughput.jsonl  one iperf3-shaped record per probe, with both positions and their distance
  mavlink.tlog      every MAVLink frame to and from the autopilot (log.tlog)
"""

from __future__ import annotations

import logging
import os
import secrets
import select
import signal
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from nac_onboard.address import parse_host_port
from nac_onboard.agent.autopilot_link import AutopilotLink
from nac_onboard.agent.config import AgentConfig, peers_state_path
from nac_onboard.agent.peers import (
    MAX_DATAGRAM_BYTES,
    SIGNED_MAGIC,
    PeerMessageError,
    PeerState,
    PeerStateFileError,
    PeerTable,
    SenderMute,
    decode_peer_state,
    encode_peer_state,
)
from nac_onboard.agent.probes import ProbeScheduler
from nac_onboard.agent.snapshot import AgentSnapshot, OwnState
from nac_onboard.agent.state_feed import REQUEST as FEED_REQUEST
from nac_onboard.agent.state_feed import encode_snapshot
from nac_onboard.agent.systemd_notify import SystemdNotifier
from nac_onboard.clock import from_env, slowed_s
from nac_onboard.flight_log import JsonlLog, TlogWriter
from nac_onboard.link.emulation import SleepEmulation
from nac_onboard.link.throughput import ThroughputServer
from nac_onboard.mavlink.client import LinkError
from nac_onboard.mavlink.dialect import M
from nac_onboard.mavlink.routing import RawEndpoint
from nac_onboard.mavlink.signing import load_signing_key
from nac_onboard.node.mpi_build import mpi_build
from nac_onboard.records import kinds

log = logging.getLogger(__name__)
EXPIRE_CHECK_S = 0.1
REJECT_LOG_PERIOD_S = 10.0
SUPERVISE_S = 1.0
MIN_WAKE_S = 0.002  # at most 500 turns of the loop a second: routed frames wait 2 ms at most for it
FLOOD_WAKE_S, FLOOD_REFUSED = 0.01, 20  # a turn that refused this many datagrams: the next waits 10 ms (a flood)
STATUSTEXT_PER_S = 10  # statustext records a second at most (an autopilot's flood is counted, not logged)
STATUSTEXT_REPEAT_S = 5.0  # the same text again within this: counted, not logged


def run_directory(config: AgentConfig, run_id: str | None = None) -> Path:
    run = run_id or config.log.run_id or os.environ.get("NAC_RUN_ID") or time.strftime("%Y%m%dT%H%M%SZ",
                                                                                        time.gmtime())
    return Path(config.log.dir) / run / config.vehicle.id


@dataclass
class _Timer:
    period_s: float
    due_s: float = 0.0

    def fire(self, now_s: float) -> bool:
        if now_s < self.due_s:
            return False
        # Keep the cadence without bursts after a stall.
        self.due_s = max(self.due_s + self.period_s, now_s)
        return True


class Agent:
    def __init__(self, config: AgentConfig, run_dir: Path, notifier: SystemdNotifier | None = None):
        self.config, self.run_dir = config, run_dir
        self.notifier = notifier or SystemdNotifier()
        self.stop_event = threading.Event()
        self.stop_reason = ""
        self.stop_requested_s: float | None = None  # unix time of the stop signal: the logs end there, not at close
        a = config.autopilot
        self.signing_key = load_signing_key(a.signing_key_file) if a.signing_key_file else None
        self.log = JsonlLog(run_dir / kinds.AGENT_LOG.name)
        self.throughput_log = JsonlLog(run_dir / kinds.THROUGHPUT_LOG.name)
        self.run_clock = from_env()
        # a sped-up run's .tlog: stamped unix time at simulated 0 plus simulated seconds (None: the wall clock)
        self.tlog_anchor_s = time.time() - self.run_clock.now_s() if self.run_clock.simulated else None
        self.tlog = TlogWriter(run_dir / kinds.TLOG.name, self._tlog_now) if config.log.tlog else None
        self.autopilot = AutopilotLink(a, config.vehicle.sysid or 1, config.vehicle.sysid or None, self.signing_key,
                                       self.log, lambda text: self.notifier.status(f"{text}; logging to {run_dir}"),
                                       self._log_sent if self.tlog is not None else None)
        self.endpoints: list[RawEndpoint] = []
        p = config.peers
        self.peers = PeerTable(config.vehicle.id, p.timeout_s, p.max_peers, p.forget_s,
                               p.replay_window_s if config.fleet_key else None,
                               peers_state_path(config) if config.fleet_key else None)
        self.boot_id = secrets.token_hex(8)  # our peer messages' boot: random per start, with seq counting from it
        self._boot_mono_s, self._seq = time.monotonic(), 0
        self.statustext = TextLimiter(STATUSTEXT_PER_S, STATUSTEXT_REPEAT_S)
        self._freshness_warned = False
        self.peer_rejects: dict[str, int] = {}  # refused peer datagrams by reason, since the start
        self._rejects_logged: dict[str, int] = {}
        self._last_reject_log_s = -1e9
        self.peer_sock = self.feed_sock = None
        self.peer_targets = [parse_host_port(t, "peers.send_to") for t in config.peers.send_to]
        self.throughput_server: ThroughputServer | None = None
        self.scheduler: ProbeScheduler | None = None
        self.counters = {"frames_in": 0, "frames_out": 0, "frames_routed": 0, "telemetry": 0, "peer_msgs": 0,
                         "bad_peer_msgs": 0, "feed_requests": 0, "bad_feed_requests": 0, "routing_refused": 0}
        self._refusals_logged, self._last_refusal_log_s = 0, -1e9
        self._last = {"mode": None, "armed": None, "landed": None, "mission_seq": None, "mission_state": None}
        self._state_lock = threading.Lock()  # the probe thread reads positions while the loop updates them

    # ---- setup and teardown ----------------------------------------------------------------------------
    def open(self) -> Agent:
        c = self.config
        self.log.write(kinds.AGENT_STARTED, vehicle=c.vehicle.id, role=c.vehicle.role, config=c.source,
                       autopilot=c.autopilot.uri, run_dir=str(self.run_dir), pid=os.getpid(),
                       host=socket.gethostname(), mpi_build=mpi_build(),
                       tlog_clock="simulated" if self.tlog_anchor_s is not None else "wall",
                       **({"tlog_anchor_s": self.tlog_anchor_s} if self.tlog_anchor_s is not None else {}))
        self.autopilot.open(time.monotonic())
        allow = tuple(parse_host_port(text, "routing.allow") for text in c.routing.allow)
        for uri, read_only in [*((u, False) for u in c.routing.endpoints), *((u, True) for u in c.routing.watch)]:
            try:
                self.endpoints.append(RawEndpoint(uri, read_only, allow))
            except LinkError as err:
                self.log.write(kinds.ROUTING_ERROR, endpoint=uri, error=str(err))
        self.peer_sock = _udp_socket(c.peers.listen, "peers.listen", broadcast=True)
        # one byte more than allowed, so a longer datagram shows as too big instead of cut short; one buffer, so a
        # refused datagram costs no allocation
        self._peer_buffer = memoryview(bytearray(MAX_DATAGRAM_BYTES + 1))
        self.sender_mute = SenderMute()
        self.feed_sock = _udp_socket(c.state_feed.listen, "state_feed.listen")
        if c.state_feed.expose:
            self.log.write(kinds.WARNING, text=f"the state feed listens on {c.state_feed.listen}: whoever reaches it "
                                                 "learns every vehicle's position")
            log.warning("state feed exposed on %s", c.state_feed.listen)
        if c.peers.allow_unsigned:
            self.log.write(kinds.WARNING,
                           text="peers.allow_unsigned: peer state from anyone on the network is believed")
        t = c.throughput
        if t.server:
            try:
                self.throughput_server = ThroughputServer(t.bind, t.port, self.run_clock).start()
            except OSError as err:
                raise OSError(f"throughput.port: cannot listen on {t.bind}:{t.port}: {err.strerror}") from None
        if t.probe:
            clock = self.run_clock
            emulation = SleepEmulation(c.emulated_channel, clock) if c.emulated_channel else None
            self.scheduler = ProbeScheduler(t, c.vehicle.id, self._probe_targets, self.snapshot,
                                            self.throughput_log, self.stop_event, emulation, clock).start()
        try:
            self.peers.load()
        except PeerStateFileError as err:  # replay protection after our restart falls back to replay_window_s
            self.log.write(kinds.WARNING, text=f"{err}: starting without it")
            log.warning("%s: starting without it", err)
        self.log.write(kinds.AGENT_READY, peers_listen=c.peers.listen, state_feed=c.state_feed.listen,
                       throughput_port=self.throughput_server.port if self.throughput_server else None,
                       probing=t.probe, probe_duty_cycle=t.duty_cycle if t.probe else None)
        self.notifier.ready(f"logging to {self.run_dir}")
        return self

    def close(self) -> None:
        self.stop_event.set()
        self.notifier.stopping()
        if self.scheduler is not None:
            self.scheduler.abort()
            self.scheduler.join(timeout_s=self.config.throughput.duration_s + 15.0)
        if self.throughput_server is not None:
            self.throughput_server.stop()
        for closable in [*self.endpoints, self.autopilot]:
            closable.close()
        for sock in (self.peer_sock, self.feed_sock):
            if sock is not None:
                sock.close()
        self._save_peer_freshness()
        pending = self.statustext.flush()
        if pending is not None:
            self.log.write(kinds.STATUSTEXT, **pending)
        self.log.write(kinds.AGENT_STOPPED, reason=self.stop_reason or "closed", peer_rejects=self.peer_rejects,
                       autopilot_refused=self.autopilot.refused, stop_requested_s=self.stop_requested_s,
                       **self.counters)
        for f in (self.log, self.throughput_log, self.tlog):
            if f is not None:
                f.close()
        self.notifier.close()

    def _tlog_now(self) -> float:
        return time.time() if self.tlog_anchor_s is None else self.tlog_anchor_s + self.run_clock.now_s()

    def _log_sent(self, frame: bytes) -> None:
        self.counters["frames_out"] += 1
        if self.tlog is not None:
            self.tlog.write(frame)

    # ---- the loop ----------------------------------------------------------------------------------------
    def run(self) -> None:
        c = self.config
        telemetry = _Timer(1.0 / c.log.telemetry_hz)
        publish = _Timer(0.0)
        self._times_in_run_time(publish)
        expire = _Timer(EXPIRE_CHECK_S)
        supervise = _Timer(SUPERVISE_S)
        sync = _Timer(c.log.fsync_s) if c.log.fsync_s > 0 else None
        watchdog = _Timer(self.notifier.watchdog_period_s) if self.notifier.watchdog_period_s else None
        woke_s, wake_s, refused = 0.0, MIN_WAKE_S, 0
        while not self.stop_event.is_set():
            now = time.monotonic()
            if now - woke_s < wake_s:  # under a flood, take datagrams in batches: each wake costs its own work
                time.sleep(woke_s + wake_s - now)
                now = time.monotonic()
            woke_s = now
            due = [t.due_s for t in (telemetry, publish, expire, sync, watchdog, supervise) if t is not None]
            autopilot = self.autopilot.readers()
            readers = [s for s in (self.peer_sock, self.feed_sock) if s is not None] + self.endpoints + autopilot
            try:
                ready, _, _ = select.select(readers, [], [], min(max(min(due) - now, 0.0), 0.5))
            except (OSError, ValueError):
                ready = readers  # a link closed under us: let each reader find out below
            now = time.monotonic()
            if not ready or any(r in autopilot for r in ready):  # on a timeout too: a closed link shows there
                self._read_autopilot(now)
            if self.endpoints and any(r in self.endpoints for r in ready):
                self._read_endpoints()
            if self.peer_sock in ready:
                self._read_peers(now)
            if self.feed_sock in ready:
                self._answer_feed(now)
            refused, before = (self.counters["bad_peer_msgs"] + self.counters["routing_refused"]
                               + self.autopilot.refused), refused
            wake_s = FLOOD_WAKE_S if refused - before >= FLOOD_REFUSED else MIN_WAKE_S
            self.autopilot.check(now)
            if telemetry.fire(now):
                self._log_telemetry()
            if publish.fire(now):
                self._publish_state()
            if expire.fire(now):
                self._times_in_run_time(publish)  # the pace can change; every expiry check follows it
                for peer, silent_s in self.peers.expire(now):
                    self.log.write(kinds.PEER_LOST, peer=peer.id, role=peer.role, host=peer.host,
                                   silent_s=round(self.run_clock.sim_s(silent_s), 3))
            if sync is not None and sync.fire(now):
                for f in (self.log, self.throughput_log, self.tlog):
                    if f is not None:
                        f.sync()
            if watchdog is not None and watchdog.fire(now):
                self.notifier.watchdog()
            if supervise.fire(now):
                self._supervise_throughput_server()
                self._save_peer_freshness()

    def _times_in_run_time(self, publish: _Timer) -> None:
        """The peer state's period and the peers' timeouts are the run's seconds (a real vehicle's are wall
        seconds): at a speed-up X the state goes X times as often on the wall clock, so a sped-up run's air carries
        what a real-time one's does (wall-clock periods put twice the frames into a simulated second at 0.25x as at
        0.5x), and a silent peer is lost after the same simulated seconds. Below 1x the autopilot link's timeout
        and the peers' replay window are stretched too: the autopilot's 1 Hz heartbeat came 5-10 wall seconds apart
        at 0.2-0.1x (a 16-vehicle fleet logged 2,700-3,000 link_lost), and a state held seconds in the slowed air's
        queues was refused as stale. Above 1x they stay wall seconds, a floor a loaded host's late wake-ups need."""
        p, wall_s = self.config.peers, self.run_clock.wall_s
        publish.period_s = wall_s(1.0 / p.rate_hz)
        self.peers.timeout_s = wall_s(p.timeout_s)
        self.peers.forget_s = wall_s(max(p.forget_s, p.timeout_s))
        speedup = self.run_clock.speedup
        self.autopilot.link_timeout_s = slowed_s(self.config.autopilot.link_timeout_s, speedup)
        if self.peers.replay_window_s is not None:
            self.peers.replay_window_s = slowed_s(p.replay_window_s, speedup)

    def stop(self, reason: str) -> None:
        self.stop_reason = reason
        self.stop_requested_s = time.time()
        self.stop_event.set()

    # ---- autopilot -----------------------------------------------------------------------------------------
    def _read_autopilot(self, now: float) -> None:
        messages = self.autopilot.read(now)
        if not messages:
            return
        frames = [msg.get_msgbuf() for msg in messages]
        self.counters["frames_in"] += len(frames)
        if self.tlog is not None:
            self.tlog.write_many(frames)
        sysid = self.autopilot.sysid
        for msg, frame in zip(messages, frames, strict=True):
            for endpoint in self.endpoints:
                if endpoint.write(frame):
                    self.counters["frames_routed"] += 1
            if msg.get_srcSystem() == sysid:
                self._on_autopilot_message(msg)

    def _on_autopilot_message(self, msg) -> None:
        kind = msg.get_type()
        vehicle = self.autopilot.vehicle()
        if vehicle is None:
            return
        if kind == "HEARTBEAT" and msg.get_srcComponent() == M.MAV_COMP_ID_AUTOPILOT1:
            self._note_change("mode", vehicle.mode)
            self._note_change("armed", vehicle.armed)
        elif kind == "MISSION_ITEM_REACHED":
            self.log.write(kinds.MISSION_ITEM_REACHED, seq=msg.seq)
        elif kind == "MISSION_CURRENT":
            self._note_change("mission_seq", msg.seq, total=vehicle.mission_total)
            if vehicle.mission_state:
                self._note_change("mission_state", vehicle.mission_state)
        elif kind == "EXTENDED_SYS_STATE":
            self._note_change("landed", vehicle.landed)
        elif kind == "STATUSTEXT":
            record = self.statustext.offer(msg.severity, msg.text, time.monotonic())
            if record is not None:
                self.log.write(kinds.STATUSTEXT, **record)

    def _note_change(self, key: str, value, **extra) -> None:
        previous = self._last[key]
        if value != previous:
            self._last[key] = value
            self.log.write(kinds.CHANGES[key], value=value, previous=previous, **extra)

    def _log_telemetry(self) -> None:
        v = self.autopilot.vehicle()
        if not self.autopilot.up or v is None:
            return  # nothing fresh to say: a lost link's last position is not today's
        if v.time_boot_ms < 0:
            return
        self.counters["telemetry"] += 1
        self.log.write(kinds.TELEMETRY, sysid=v.sysid, time_boot_ms=v.time_boot_ms, lat_deg=v.lat_deg,
                       lon_deg=v.lon_deg, alt_m=v.alt_m, rel_alt_m=v.rel_alt_m, vel_ned_mps=v.vel_ned_mps,
                       roll_deg=round(v.roll_deg, 3), pitch_deg=round(v.pitch_deg, 3), yaw_deg=round(v.yaw_deg, 3),
                       battery_pct=v.battery_pct, voltage_v=v.voltage_v, mode=v.mode, armed=v.armed,
                       landed=v.landed, mission_seq=v.mission_seq, mission_total=v.mission_total)

    def _save_peer_freshness(self) -> None:
        """Keep the last sequence accepted per peer on disk (at most once a second, and at the stop)."""
        try:
            with self._state_lock:
                self.peers.save()
        except OSError as err:
            if not self._freshness_warned:
                self._freshness_warned = True
                self.log.write(kinds.WARNING, text=f"cannot save {self.peers.freshness_path}: {err.strerror}: "
                                                   "after a restart, peers are judged by replay_window_s alone")

    def _supervise_throughput_server(self) -> None:
        """A server thread that died is started again on its port: without it every probe would read as a lost
        link. Each restart is an event in the log."""
        server = self.throughput_server
        if server is None or server.alive:
            return
        t = self.config.throughput
        try:
            server.stop()
            self.throughput_server = ThroughputServer(t.bind, t.port, self.run_clock).start()
            self.log.write(kinds.THROUGHPUT_SERVER_RESTARTED, port=t.port, refused_before=server.refused)
        except OSError as err:
            self.log.write(kinds.THROUGHPUT_SERVER_FAILED, port=t.port, error=str(err))

    # ---- routing -------------------------------------------------------------------------------------------
    def _read_endpoints(self) -> None:
        for endpoint in self.endpoints:
            for frame in endpoint.read_frames():
                self.autopilot.write_frame(frame)
                for other in self.endpoints:
                    if other is not endpoint:
                        other.write(frame)
                self.counters["frames_routed"] += 1
                if self.tlog is not None:
                    self.tlog.write(frame)
        dropped = self.counters["routing_refused"] = sum(e.dropped_frames for e in self.endpoints)
        now = time.monotonic()
        if dropped > self._refusals_logged and now - self._last_refusal_log_s >= REJECT_LOG_PERIOD_S:
            senders = sorted({e.last_dropped_sender for e in self.endpoints if e.last_dropped_sender})
            self.log.write(kinds.ROUTING_REFUSED, frames_since_last_record=dropped - self._refusals_logged,
                           senders=senders)
            self._refusals_logged, self._last_refusal_log_s = dropped, now

    # ---- peers and the state feed ----------------------------------------------------------------------------
    def own_state(self) -> PeerState:
        c = self.config
        v = self.autopilot.vehicle()
        known = v is not None and v.time_boot_ms >= 0
        port = self.throughput_server.port if self.throughput_server else 0
        with self._state_lock:  # the probe thread asks too: each message its own, strictly increasing seq
            self._seq = max(self._seq + 1, int((time.monotonic() - self._boot_mono_s) * 1000))
            seq = self._seq
        if not known:
            return PeerState(id=c.vehicle.id, role=c.vehicle.role, t_s=time.time(), sysid=self.autopilot.sysid or 0,
                             probe_port=port, mpi_build=mpi_build(), boot=self.boot_id, seq=seq)
        return PeerState(id=c.vehicle.id, role=c.vehicle.role, t_s=time.time(), sysid=v.sysid, lat_deg=v.lat_deg,
                         lon_deg=v.lon_deg, alt_m=v.alt_m, vel_ned_mps=tuple(v.vel_ned_mps),
                         battery_pct=v.battery_pct, probe_port=port, mpi_build=mpi_build(), boot=self.boot_id,
                         seq=seq)

    def _publish_state(self) -> None:
        data = encode_peer_state(self.own_state(), self.config.fleet_key)
        for target in self.peer_targets:
            try:
                self.peer_sock.sendto(data, target)
            except OSError:
                pass  # no route yet (Wi-Fi not associated): the next period tries again

    def _read_peers(self, now: float) -> None:
        key, allow_unsigned = self.config.fleet_key, self.config.peers.allow_unsigned
        buffer, receive, magic = self._peer_buffer, self.peer_sock.recvfrom_into, len(SIGNED_MAGIC)
        mute, muted, muted_host = self.sender_mute, 0, ""
        while True:
            try:
                size, sender = receive(buffer)
            except (BlockingIOError, InterruptedError):
                if muted:
                    self._peer_rejected("muted", muted_host, now, muted)
                return
            host = sender[0]
            if mute.muted_until and mute.muted(sender, now):
                muted, muted_host = muted + 1, host  # counted once per batch: the cheapest path of all
                continue
            if key is not None and not allow_unsigned and buffer[:magic] != SIGNED_MAGIC \
                    and size <= MAX_DATAGRAM_BYTES:
                reason = "unsigned"  # the cheapest refusal first: a flood is mostly these
            else:
                try:
                    peer = decode_peer_state(bytes(buffer[:size]), host, key, allow_unsigned)
                    with self._state_lock:
                        seen = self.peers.update(peer, now, time.time())
                    reason = None
                except PeerMessageError as err:
                    reason = err.reason
            if reason is not None:
                self._peer_rejected(reason, host, now)
                mute.refused(sender, now)  # the rate-limited peer_rejected record counts what muting then drops
                continue
            self.counters["peer_msgs"] += 1
            if seen:
                self.log.write(kinds.PEER_SEEN, peer=peer.id, role=peer.role, host=host, probe_port=peer.probe_port)

    def _peer_rejected(self, reason: str, host: str, now: float, count: int = 1) -> None:
        """Count it; log at most one peer_rejected record per REJECT_LOG_PERIOD_S, with the counts since the last."""
        self.counters["bad_peer_msgs"] += count
        self.peer_rejects[reason] = self.peer_rejects.get(reason, 0) + count
        if now - self._last_reject_log_s >= REJECT_LOG_PERIOD_S:
            since = {r: n - self._rejects_logged.get(r, 0) for r, n in self.peer_rejects.items()
                     if n != self._rejects_logged.get(r, 0)}
            self.log.write(kinds.PEER_REJECTED, last_sender=host, last_reason=reason, since_last_record=since)
            self._rejects_logged = dict(self.peer_rejects)
            self._last_reject_log_s = now

    def snapshot(self) -> AgentSnapshot:
        """This vehicle and every peer, with ages: what the state feed answers and the probes log."""
        own = OwnState.of(self.own_state(), self.autopilot.up)
        with self._state_lock:
            peers = tuple(self.peers.snapshot(time.monotonic()).values())
        probes = self.scheduler.results() if self.scheduler is not None else ()
        return AgentSnapshot(time.time(), own, peers, probes)

    def _answer_feed(self, now: float) -> None:
        while True:
            try:
                request, sender = self.feed_sock.recvfrom(512)
            except (BlockingIOError, InterruptedError):
                return
            if request != FEED_REQUEST:  # anything else gets nothing back: no reflection, no amplification
                self.counters["bad_feed_requests"] += 1
                continue
            self.counters["feed_requests"] += 1
            try:
                self.feed_sock.sendto(encode_snapshot(self.snapshot()), sender)
            except (OSError, ValueError) as err:
                log.warning("state feed answer to %s failed: %s", sender, err)

    def _probe_targets(self) -> list[tuple[str, str, int]]:
        t = self.config.throughput
        if t.targets:
            out = []
            for target in t.targets:
                name, _, address = target.partition("=")
                host, port = parse_host_port(address, "throughput.targets")
                out.append((name, host, port))
            return out
        with self._state_lock:
            live = self.peers.live()
        return [(p.id, p.host, p.probe_port) for p in live if p.role == "worker" and p.probe_port]


class TextLimiter:
    """Which of an autopilot's STATUSTEXTs to log: the same text again within repeat_s is counted, not logged (its
    count goes on the next record as `repeated`); beyond per_s records a second, others are counted, not logged
    (`dropped_since_last` on the next record). A flood of texts then grows the log by per_s records a second."""

    def __init__(self, per_s: int, repeat_s: float):
        self.per_s, self.repeat_s = per_s, repeat_s
        self._last: tuple | None = None  # (severity, text) of the last record
        self._last_logged_s = -1e18
        self._logged_s: deque[float] = deque(maxlen=per_s)  # when the last per_s records were written
        self.repeated = self.dropped = 0  # since the last record

    def offer(self, severity: int, text: str, now_s: float) -> dict | None:
        """The record's fields to write for this text, or None when it is only counted."""
        key = (severity, text)
        if key == self._last and now_s - self._last_logged_s < self.repeat_s:
            self.repeated += 1
            return None
        if len(self._logged_s) == self.per_s and now_s - self._logged_s[0] < 1.0:  # per_s in the last second
            if key == self._last:
                self.repeated += 1
            else:
                self.dropped += 1
            return None
        self._logged_s.append(now_s)
        return self._record(key, now_s)

    def flush(self) -> dict | None:
        """At the stop: a last record carrying what was counted since the last, if anything."""
        if self._last is None or not (self.repeated or self.dropped):
            return None
        return {**self._record(self._last, self._last_logged_s), "counts_only": True}

    def _record(self, key: tuple, now_s: float) -> dict:
        record = {"severity": key[0], "text": key[1]}
        if self.repeated:
            record["repeated"] = self.repeated
        if self.dropped:
            record["dropped_since_last"] = self.dropped
        self._last, self._last_logged_s, self.repeated, self.dropped = key, now_s, 0, 0
        return record


def _udp_socket(address: str, key: str, broadcast: bool = False) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    if broadcast:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    try:
        sock.bind(parse_host_port(address, key, allow_port_zero=True))
    except OSError as err:
        sock.close()
        raise OSError(f"{key}: cannot listen on {address}: {err.strerror}") from None
    sock.setblocking(False)
    return sock


def run_agent(config: AgentConfig, run_id: str | None = None, ready_line=None) -> int:
    """Run until SIGTERM or SIGINT; returns the exit code (0 on a clean stop)."""
    run_dir = run_directory(config, run_id)
    agent = Agent(config, run_dir)
    previous = {}
    # Past a file-size limit a write fails with EFBIG, and the log handles that; SIGXFSZ would end the agent first.
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    def on_signal(signum, _frame):
        agent.stop(signal.Signals(signum).name)

    for signum in (signal.SIGTERM, signal.SIGINT):
        previous[signum] = signal.signal(signum, on_signal)
    try:
        agent.open()
        if ready_line is not None:
            ready_line(f"nac-onboard agent {config.vehicle.id} ({config.vehicle.role}) ready: logging to {run_dir}")
        agent.run()
    finally:
        agent.close()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0
