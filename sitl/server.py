"""The SITL server: sockets, simulated clock with speed-up, the step loop, faults and the Python API.

One thread runs everything: physics steps (vectorised), flight logic, telemetry due at simulated-time rates,
and socket I/O between steps. API calls from other threads take the same lock.
"""

from __future__ import annotations

import errno
import logging
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field, replace

import numpy as np

from missions.geo import Home, enu_to_lla, enu_to_lla_many, lla_to_enu, offset_home
from sitl.mavlink.codec import new_parser, parse_datagram
from sitl.mavlink.vehicle_protocol import DEFAULT_INTERVALS_S, STREAM_IDS, VehicleLink
from sitl.vehicle.flight import Check, CopterMode, Fleet
from sitl.vehicle.params import ParamTable
from sitl.vehicle.physics import Motion, VehicleState, attitude_rad, gps_noise_m, step

log = logging.getLogger(__name__)

GROUND, COMPANION = "ground", "companion"
MAX_DATAGRAM_BYTES = 1200  # below a typical MTU once IP/UDP headers are added
LINK_BITS = {GROUND: 1, COMPANION: 2}


class SitlError(RuntimeError):
    """The simulator could not start (e.g. a port is taken); the message says which and why."""


@dataclass(frozen=True)
class SitlConfig:
    vehicles: int = 1
    speedup: float = 1.0
    home: Home = Home(47.397742, 8.545594, 488.0)
    spacing_m: float = 5.0  # vehicle i's home is i * spacing_m east of `home`
    vehicle_homes: tuple = ()  # one Home per vehicle, overriding home and spacing_m (e.g. from mission plans)
    seed: int = 0
    params: dict = field(default_factory=dict)
    host: str = "127.0.0.1"  # where the UDP links are sent
    gcs_base_port: int = 14550
    companion_base_port: int = 14551
    tcp_base_port: int = 5760  # 0 = no TCP server
    port_step: int = 10
    extra_outs: tuple = ()  # ((host, base_port), ...): more ground links, port + port_step * i
    dt_s: float = 0.01
    signing_key: bytes | None = None  # MAVLink 2 signing: sign everything sent, refuse unsigned input


class Channel:
    """One MAVLink link of one vehicle: a UDP socket with a fixed peer, or an accepted TCP connection."""

    def __init__(self, sim: Sitl, vehicle: int, kind: str, sock: socket.socket, peer=None, tcp: bool = False):
        self.sim, self.vehicle, self.kind = sim, vehicle, kind
        self.sock, self.peer, self.tcp = sock, peer, tcp
        self.parser = new_parser(sim.config.signing_key)
        self.closed = False
        self.pending: list[bytes] = []
        self.pending_bytes = 0

    def describe(self) -> str:
        if self.tcp:
            return f"tcp client {self.peer[0]}:{self.peer[1]}"
        return f"udp {self.peer[0]}:{self.peer[1]}"

    def write(self, frame: bytes) -> None:
        """Queue a frame; frames queued within one step leave together in one datagram, as ArduPilot's
        UDP links pack them, which saves a system call per message."""
        if self.closed or not self.sim.link_passes(self.vehicle, self.kind):
            return
        self.pending.append(frame)
        self.pending_bytes += len(frame)
        if self.pending_bytes >= MAX_DATAGRAM_BYTES:
            self.flush()
        else:
            self.sim.dirty.add(self)

    def flush(self) -> None:
        if not self.pending:
            return
        data = b"".join(self.pending)
        self.pending.clear()
        self.pending_bytes = 0
        try:
            if self.tcp:
                self.sock.send(data)
            else:
                self.sock.sendto(data, self.peer)
        except BlockingIOError:
            pass  # a slow TCP reader loses telemetry, as over a real radio
        except OSError as err:
            if self.tcp:
                self.sim.drop_channel(self)
            elif err.errno not in (errno.ECONNREFUSED, errno.ENETUNREACH, errno.EHOSTUNREACH):
                log.debug("vehicle %d %s: %s", self.vehicle + 1, self.describe(), err)

    def feed(self, data: bytes) -> None:
        if not self.sim.link_passes(self.vehicle, self.kind):
            return
        try:
            if self.tcp:
                messages = self.parser.parse_buffer(data) or []
            else:
                messages = parse_datagram(self.parser, data)
        except Exception as err:  # pymavlink raises on some malformed input even in robust mode
            self.sim.stats["bad_frames"] += 1
            log.debug("vehicle %d: unparseable input: %s", self.vehicle + 1, err)
            self.parser = new_parser(self.sim.config.signing_key)
            return
        link = self.sim.links[self.vehicle]
        for msg in messages:
            if msg.get_type() == "BAD_DATA":
                self.sim.stats["bad_frames"] += 1
                continue
            try:
                link.handle(msg, self)
            except Exception:  # a message the handlers did not foresee must not stop the simulator
                self.sim.stats["handler_errors"] += 1
                log.exception("vehicle %d: error handling %s", self.vehicle + 1, msg.get_type())


@dataclass
class Telemetry:
    """Per-step snapshot of what the vehicles report, computed once for all of them."""

    state: VehicleState
    time_boot_ms: int
    time_usec: int
    lat_e7: list
    lon_e7: list
    alt_mm: list
    rel_alt_mm: list
    vn_cms: list
    ve_cms: list
    vd_cms: list
    hdg_cdeg: list
    roll: list
    pitch: list
    yaw: list
    landed_state: list


class Sitl:
    def __init__(self, config: SitlConfig):
        self.config = config
        n = config.vehicles
        if n < 1:
            raise SitlError("need at least one vehicle")
        if config.vehicle_homes and len(config.vehicle_homes) != n:
            raise SitlError(f"vehicle_homes: {len(config.vehicle_homes)} homes for {n} vehicles")
        self.homes = list(config.vehicle_homes) or [offset_home(config.home, i * config.spacing_m, 0.0)
                                                    for i in range(n)]
        self._home_lat = np.array([h.lat_deg for h in self.homes])
        self._home_lon = np.array([h.lon_deg for h in self.homes])
        self._home_alt = np.array([h.alt_m for h in self.homes])
        self.params = ParamTable(n)
        self.params.values[:, self.params.index("SIM_SPEEDUP")] = config.speedup
        for name, value in config.params.items():
            for i in range(n):
                self.params.set(i, name, float(value))
        self.physics = self.params.physics()
        self.state = VehicleState.at_rest(n, self.physics)
        self.fleet = Fleet(self.homes, self.params)
        self.fleet.state = self.state
        self.rng = np.random.default_rng(config.seed)
        self.t_s = 0.0
        self.epoch_unix_s = time.time()
        self.stats = {"bad_frames": 0, "handler_errors": 0, "io_errors": 0, "steps": 0, "overruns": 0}
        self.stream_interval_s = np.tile(np.array([DEFAULT_INTERVALS_S[m] for m in STREAM_IDS]), (n, 1))
        self.links = [VehicleLink(i, self.fleet, self) for i in range(n)]
        self.stream_next_due_s = np.zeros((n, len(STREAM_IDS)))
        self._telemetry: Telemetry | None = None
        self._last_fix_m = self.state.pos_m.copy()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._selector = selectors.DefaultSelector()
        self._sockets: list[socket.socket] = []
        self.endpoints: list[dict[str, str]] = []
        self.dirty: set[Channel] = set()  # channels with frames queued
        self.step_observers: list = []  # callables (t_s, state) run after every step, under the lock
        self._apply_param_side_effects()
        self._open_sockets()

    # ---- sockets ------------------------------------------------------------------------------------
    def _udp(self, vehicle: int, kind: str, host: str, port: int) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        sock.bind(("0.0.0.0", 0))
        channel = Channel(self, vehicle, kind, sock, (host, port))
        self.links[vehicle].channels.append(channel)
        self._selector.register(sock, selectors.EVENT_READ, ("udp", channel))
        self._sockets.append(sock)

    def _open_sockets(self) -> None:
        c = self.config
        try:
            for i in range(c.vehicles):
                gcs_port = c.gcs_base_port + c.port_step * i
                cc_port = c.companion_base_port + c.port_step * i
                self._udp(i, GROUND, c.host, gcs_port)
                self._udp(i, COMPANION, c.host, cc_port)
                ends = {"ground": f"udp {c.host}:{gcs_port}", "companion": f"udp {c.host}:{cc_port}"}
                for host, base in c.extra_outs:
                    self._udp(i, GROUND, host, base + c.port_step * i)
                    ends.setdefault("out", "")
                    ends["out"] += f"udp {host}:{base + c.port_step * i} "
                if c.tcp_base_port:
                    port = c.tcp_base_port + c.port_step * i
                    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
                    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                    try:
                        server.bind(("0.0.0.0", port))
                    except OSError as err:
                        server.close()
                        raise SitlError(f"TCP port {port} for vehicle {i + 1} is taken ({err.strerror}); "
                                        f"choose another --tcp-base-port") from None
                    server.listen(4)
                    server.setblocking(False)
                    self._selector.register(server, selectors.EVENT_READ, ("listen", (server, i)))
                    self._sockets.append(server)
                    ends["tcp"] = f"0.0.0.0:{port}"
                self.endpoints.append(ends)
        except Exception:
            self._close_sockets()
            raise

    def _accept(self, server: socket.socket, vehicle: int) -> None:
        try:
            conn, addr = server.accept()
        except OSError:
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        channel = Channel(self, vehicle, GROUND, conn, addr, tcp=True)
        self.links[vehicle].channels.append(channel)
        self._selector.register(conn, selectors.EVENT_READ, ("tcp", channel))
        self._sockets.append(conn)
        log.info("vehicle %d: TCP client %s:%d connected", vehicle + 1, *addr)

    def drop_channel(self, channel: Channel) -> None:
        if channel.closed:
            return
        channel.closed = True
        link = self.links[channel.vehicle]
        if channel in link.channels:
            link.channels.remove(channel)
        try:
            self._selector.unregister(channel.sock)
        except (KeyError, ValueError):
            pass
        channel.sock.close()

    def _close_sockets(self) -> None:
        for sock in self._sockets:
            try:
                self._selector.unregister(sock)
            except (KeyError, ValueError):
                pass
            sock.close()
        self._sockets.clear()

    def _read(self, kind: str, target) -> None:
        if kind == "listen":
            self._accept(target[0], target[1])
            return
        channel: Channel = target
        for _ in range(64):  # bounded so one flooding peer cannot starve the clock
            try:
                if channel.tcp:
                    data = channel.sock.recv(65536)
                    if not data:
                        self.drop_channel(channel)
                        return
                else:
                    data, _addr = channel.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                if channel.tcp:
                    self.drop_channel(channel)
                return
            channel.feed(data)
            if channel.closed:
                return

    # ---- faults and links ---------------------------------------------------------------------------
    def link_passes(self, vehicle: int, kind: str) -> bool:
        if not self._faults_active:
            return True
        values = self.params.values[vehicle]
        if int(values[self._col_down]) & LINK_BITS[kind]:
            return False
        loss_pct = values[self._col_loss_gcs if kind == GROUND else self._col_loss_cc]
        return loss_pct <= 0 or self.rng.random() * 100.0 >= loss_pct

    def flush(self) -> None:
        """Send everything queued on every channel."""
        while self.dirty:
            self.dirty.pop().flush()

    def _apply_param_side_effects(self) -> None:
        p = self.params
        self._col_down = p.index("SIM_LINK_DOWN")
        self._col_loss_gcs = p.index("SIM_LOSS_GCS")
        self._col_loss_cc = p.index("SIM_LOSS_CC")
        self._faults_active = bool(p.values[:, [self._col_down, self._col_loss_gcs, self._col_loss_cc]].any())
        self.physics = p.physics()
        self.fleet.gps_ok = p.column("SIM_GPS_DISABLE") < 0.5
        self.fleet.on_params_changed()
        for link, retry_ms in zip(self.links, p.column("SIM_MIS_RETRY_MS"), strict=True):
            link.receiver.item_timeout_s = retry_ms / 1000.0
        batt = p.column("SIM_BATT_PCT")
        override = batt >= 0
        if override.any():
            soc = self.state.soc.copy()
            soc[override] = batt[override] / 100.0
            self.state = replace(self.state, soc=soc)
            p.values[override, p.index("SIM_BATT_PCT")] = -1  # applied once, like a battery swap

    def set_param(self, vehicle: int, name: str, value: float) -> None:
        with self._lock:
            self.params.set(vehicle, name, value)
            self._apply_param_side_effects()

    def set_loss(self, vehicle: int, link: str, pct: float) -> None:
        """Drop pct % of packets both ways on the 'ground' or 'companion' link."""
        self.set_param(vehicle, "SIM_LOSS_GCS" if link == GROUND else "SIM_LOSS_CC", pct)

    def set_link_down(self, vehicle: int, link: str, down: bool) -> None:
        with self._lock:
            bits = int(self.params.get(vehicle, "SIM_LINK_DOWN"))
            bits = bits | LINK_BITS[link] if down else bits & ~LINK_BITS[link]
            self.set_param(vehicle, "SIM_LINK_DOWN", bits)

    def set_gps_lost(self, vehicle: int, lost: bool) -> None:
        self.set_param(vehicle, "SIM_GPS_DISABLE", 1 if lost else 0)

    def set_battery_pct(self, vehicle: int, pct: float) -> None:
        self.set_param(vehicle, "SIM_BATT_PCT", pct)

    # ---- clock and state ----------------------------------------------------------------------------
    def wall_s(self) -> float:
        return time.monotonic()

    def unix_time_s(self) -> float:
        return self.epoch_unix_s + self.t_s

    def global_to_enu(self, vehicle: int, lat: float, lon: float, alt: float, relative: bool = True) -> np.ndarray:
        home = self.homes[vehicle]
        enu = lla_to_enu(lat, lon, home.alt_m, home)
        enu[2] = alt if relative else alt - home.alt_m
        return enu

    def truth(self, vehicle: int) -> dict:
        """True state of one vehicle (for tests and tools): ENU about its home, geodetic, mode, armed."""
        with self._lock:
            s = self.state
            lat, lon, alt = enu_to_lla(s.pos_m[vehicle], self.homes[vehicle])
            f = self.fleet
            return {
                "t_s": self.t_s, "pos_m": s.pos_m[vehicle].copy(), "vel_mps": s.vel_mps[vehicle].copy(),
                "lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt),
                "rel_alt_m": float(s.pos_m[vehicle, 2]), "on_ground": bool(s.on_ground[vehicle]),
                "armed": bool(f.armed[vehicle]), "mode": CopterMode(int(f.mode[vehicle])).name,
                "soc": float(s.soc[vehicle]), "mission_seq": int(f.current_seq[vehicle]),
                "mission_state": int(f.mission_state[vehicle]),
            }

    def telemetry(self) -> Telemetry:
        if self._telemetry is None or self._telemetry.time_boot_ms != int(self.t_s * 1000):
            self._telemetry = self._snapshot()
        return self._telemetry

    def _snapshot(self) -> Telemetry:
        s = self.state
        n = self.config.vehicles
        fix = self.fleet.gps_ok
        self._last_fix_m[fix] = s.pos_m[fix]
        sigma = self.params.column("SIM_GPS_NOISE")
        reported = self._last_fix_m
        if sigma.any():
            reported = reported + gps_noise_m(self.rng, n, 1.0, 1.5) * sigma[:, None]
        lat, lon, _ = enu_to_lla_many(reported, self._home_lat, self._home_lon, self._home_alt)
        roll, pitch, yaw = attitude_rad(s)
        hdg = np.mod(np.degrees(yaw), 360.0)
        landed = np.where(s.on_ground, 1, np.where(self.fleet.motion == Motion.LAND, 4, 2))
        climbing = (self.fleet.check == Check.ALTITUDE) & ~s.on_ground
        landed = np.where(climbing, 3, landed)
        return Telemetry(
            state=s, time_boot_ms=int(self.t_s * 1000), time_usec=int(self.unix_time_s() * 1e6),
            lat_e7=np.round(lat * 1e7).astype(np.int64).tolist(),
            lon_e7=np.round(lon * 1e7).astype(np.int64).tolist(),
            alt_mm=np.round((self._home_alt + reported[:, 2]) * 1000).astype(np.int64).tolist(),
            rel_alt_mm=np.round(reported[:, 2] * 1000).astype(np.int64).tolist(),
            vn_cms=np.round(s.vel_mps[:, 1] * 100).astype(np.int64).tolist(),
            ve_cms=np.round(s.vel_mps[:, 0] * 100).astype(np.int64).tolist(),
            vd_cms=np.round(-s.vel_mps[:, 2] * 100).astype(np.int64).tolist(),
            hdg_cdeg=np.round(hdg * 100).astype(np.int64).tolist(),
            roll=roll.tolist(), pitch=pitch.tolist(), yaw=yaw.tolist(), landed_state=landed.tolist(),
        )

    # ---- the loop -----------------------------------------------------------------------------------
    def step_once(self) -> None:
        """Advance the simulation by one physics step and send what falls due (call with the lock held)."""
        dt = self.config.dt_s
        self.state = step(self.state, self.fleet.command(), self.physics, dt)
        self.t_s += dt
        self.stats["steps"] += 1
        self.fleet.update(self.state, self.t_s)
        for observe in self.step_observers:
            observe(self.t_s, self.state)
        if self.fleet.events:
            events, self.fleet.events = self.fleet.events, []
            for vehicle, kind, value in events:
                self.links[vehicle].on_event(kind, value)
        due = self.stream_next_due_s <= self.t_s
        if due.any():
            telemetry = self.telemetry()
            interval = self.stream_interval_s[due]
            self.stream_next_due_s[due] = np.maximum(self.stream_next_due_s[due] + interval, self.t_s)
            rows, columns = np.nonzero(due)
            for vehicle, column in zip(rows.tolist(), columns.tolist(), strict=True):
                link = self.links[vehicle]
                link.send(link.build(STREAM_IDS[column], telemetry))

    def run(self) -> None:
        """Run until stop() (blocks the calling thread)."""
        dt = self.config.dt_s
        speedup = self.config.speedup
        wall0, sim0 = time.monotonic(), self.t_s
        while not self._stop.is_set():
            with self._lock:
                target = sim0 + (time.monotonic() - wall0) * speedup
                steps = 0
                while self.t_s + dt <= target and steps < 20:
                    self.step_once()
                    steps += 1
                self.flush()
                if target - self.t_s > 0.5 * speedup:  # fell behind by half a second: slip, don't spiral
                    self.stats["overruns"] += 1
                    wall0, sim0 = time.monotonic(), self.t_s
                now = time.monotonic()
                for link in self.links:
                    link.poll_transfers(now)
            wait_s = min(max((self.t_s + dt - target) / speedup, 0.0), 0.02)
            for key, _ in self._selector.select(wait_s):
                with self._lock:
                    try:
                        self._read(*key.data)
                    except Exception:  # one bad socket event must not stop every vehicle
                        self.stats["io_errors"] += 1
                        log.exception("error reading %s", key.data[0])
                    self.flush()

    def start(self) -> Sitl:
        """Run in a background thread (in-process use, tests)."""
        self._thread = threading.Thread(target=self._run_safely, name="nac-sitl", daemon=True)
        self._thread.start()
        return self

    def _run_safely(self) -> None:
        try:
            self.run()
        except Exception:
            log.exception("SITL loop stopped by an error")
            raise

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self._close_sockets()
        self._selector.close()

    def __enter__(self) -> Sitl:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
