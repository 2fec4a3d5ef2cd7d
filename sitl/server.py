"""The SITL server: sockets, the pacing of simulated time against the wall clock, and the fault API.

One thread runs everything: world steps (sitl.vehicle, vectorised), telemetry due at simulated-time rates
(sitl.mavlink), and socket I/O between steps. API calls from other threads take the same lock.
"""

from __future__ import annotations

import errno
import logging
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from missions.geo import Home, lla_to_enu
from nac_onboard.address import is_loopback
from nac_onboard.errors import OperationFailed
from nac_onboard.mavlink.signing import SigningState
from sitl.mavlink.codec import new_parser, parse_datagram
from sitl.mavlink.telemetry import Streams, TelemetrySource
from sitl.mavlink.vehicle_protocol import VehicleProtocol
from sitl.network.netns import socket_in_netns
from sitl.telemetry_radio import TELEMETRY_RADIOS
from sitl.vehicle.world import COMPANION, GROUND, World

log = logging.getLogger(__name__)

MAX_DATAGRAM_BYTES = 1200  # below a typical MTU once IP/UDP headers are added
# Caught up with the clock, what a step queued leaves at once; running behind it (more vehicles or a higher
# speed-up than this core can step), frames wait up to this long to share datagrams: 200 links at 100 vehicles
# cost a quarter of the time in send() with a datagram per link every 20 steps.
BEHIND_FLUSH_S = 0.05
KEEPING_UP_S = 0.05  # wall: a world this close behind its pacing line is keeping up (a loaded host wakes it late)


class SitlError(OperationFailed):
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
    tcp_bind: str = "127.0.0.1"  # where the TCP server listens; another address exposes the vehicles to that network
    port_step: int = 10
    extra_outs: tuple = ()  # ((host, base_port), ...): more ground links, port + port_step * i
    dt_s: float = 0.01
    signing_key: bytes | None = None  # MAVLink 2 signing: sign everything sent, refuse unsigned input
    signing_state_file: str | None = None  # where the signing timestamps outlive a restart (beside the key file)
    # One network namespace per vehicle (a simulated companion computer): its companion link is a UDP socket on
    # that namespace's loopback, as a serial or UDP link between a Pixhawk and a Jetson is off the Wi-Fi.
    companion_netns: tuple[str, ...] = ()
    # The ground link's radio (sitl.telemetry_radio.TELEMETRY_RADIOS, e.g. "sik-915"): frames are lost with
    # the distance to the ground station, as over a telemetry radio; "" = a lossless link (SITL's default).
    telemetry_radio: str = ""
    ground_station: Home | None = None  # where the ground station's antenna is (None: at each vehicle's home)
    frames: tuple = ()  # an energy.Frame per vehicle from a frame file, overriding NAC_FRAME (none: NAC_FRAME's)


class Connection:
    """One client of one vehicle's link: a UDP socket with a fixed peer, or an accepted TCP connection."""

    def __init__(self, sim: Sitl, vehicle: int, kind: str, sock: socket.socket, peer=None, tcp: bool = False):
        self.sim, self.vehicle, self.kind = sim, vehicle, kind
        self.sock, self.peer, self.tcp = sock, peer, tcp
        self.parser = new_parser(sim.signing)
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
            self.sock.send(data)  # UDP sockets are connected to their one client
        except BlockingIOError:
            pass  # a slow TCP reader loses telemetry, as over a real radio
        except OSError as err:
            if self.tcp:
                self.sim.drop_connection(self)
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
            self.parser = new_parser(self.sim.signing)
            return
        protocol = self.sim.protocols[self.vehicle]
        for msg in messages:
            if msg.get_type() == "BAD_DATA":
                self.sim.stats["bad_frames"] += 1
                continue
            try:
                protocol.handle(msg, self)
            except Exception:  # a message the handlers did not foresee must not stop the simulator
                self.sim.stats["handler_errors"] += 1
                log.exception("vehicle %d: error handling %s", self.vehicle + 1, msg.get_type())


class Sitl:
    def __init__(self, config: SitlConfig):
        self.config = config
        n = config.vehicles
        if n < 1:
            raise SitlError("need at least one vehicle")
        if config.vehicle_homes and len(config.vehicle_homes) != n:
            raise SitlError(f"vehicle_homes: {len(config.vehicle_homes)} homes for {n} vehicles")
        homes = list(config.vehicle_homes) or World.spaced_homes(config.home, n, config.spacing_m)
        if config.frames and len(config.frames) != n:
            raise SitlError(f"frames: {len(config.frames)} frames for {n} vehicles")
        self.world = World(homes, config.params, config.seed, config.speedup, config.frames)
        self.streams = Streams(n)
        self.telemetry = TelemetrySource(self.world, time.time())
        self.signing = SigningState(config.signing_key, config.signing_state_file) if config.signing_key else None
        self.protocols = [VehicleProtocol(i, self.world, self.streams, self.telemetry, self.signing)
                          for i in range(n)]
        self.world.param_listeners.append(self._on_params_changed)
        self._faults_active = self.world.any_link_fault()
        self.telemetry_radio = None
        if config.telemetry_radio:
            if config.telemetry_radio not in TELEMETRY_RADIOS:
                raise SitlError(f"telemetry radio {config.telemetry_radio!r}: known ones are "
                                f"{', '.join(TELEMETRY_RADIOS)}")
            self.telemetry_radio = TELEMETRY_RADIOS[config.telemetry_radio]
            station = config.ground_station
            self._station_enu = np.array([lla_to_enu(station.lat_deg, station.lon_deg, home.alt_m, home)
                                          if station else np.zeros(3) for home in homes])
        self.ground_loss = np.zeros(n)  # each vehicle's ground-link frame loss this step (telemetry radio)
        self.stats = {"bad_frames": 0, "handler_errors": 0, "io_errors": 0, "steps": 0, "overruns": 0,
                      "radio_lost": 0}
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._speedup = config.speedup  # set_speedup changes it while running
        self._pacing = (time.monotonic(), 0.0, config.speedup)  # the line run() paces by: (wall0, sim0, speedup)
        self._paced_s = 0.0
        self._thread: threading.Thread | None = None
        self._selector = selectors.DefaultSelector()
        self._sockets: list[socket.socket] = []
        self.endpoints: list[dict[str, str]] = []
        self.dirty: set[Connection] = set()  # connections with frames queued
        self._open_sockets()

    # ---- sockets ------------------------------------------------------------------------------------
    def _udp(self, vehicle: int, kind: str, host: str, port: int) -> None:
        if kind == COMPANION and self.config.companion_netns:
            sock = socket_in_netns(self.config.companion_netns[vehicle], socket.AF_INET, socket.SOCK_DGRAM)
        else:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.setblocking(False)
        # Connected to its client: the kernel then delivers only that client's datagrams, so nobody else on the
        # network can command the vehicle through this link (ArduPilot SITL's --out links answer anyone).
        sock.bind(("127.0.0.1" if is_loopback(host) else "0.0.0.0", 0))
        sock.connect((host, port))
        connection = Connection(self, vehicle, kind, sock, (host, port))
        self.protocols[vehicle].connections.append(connection)
        self._selector.register(sock, selectors.EVENT_READ, ("udp", connection))
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
                        server.bind((c.tcp_bind, port))
                    except OSError as err:
                        server.close()
                        raise SitlError(f"TCP port {port} for vehicle {i + 1} is taken ({err.strerror}); "
                                        f"choose another --tcp-base-port") from None
                    server.listen(4)
                    server.setblocking(False)
                    self._selector.register(server, selectors.EVENT_READ, ("listen", (server, i)))
                    self._sockets.append(server)
                    ends["tcp"] = f"{c.tcp_bind}:{port}"
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
        connection = Connection(self, vehicle, GROUND, conn, addr, tcp=True)
        self.protocols[vehicle].connections.append(connection)
        self._selector.register(conn, selectors.EVENT_READ, ("tcp", connection))
        self._sockets.append(conn)
        log.info("vehicle %d: TCP client %s:%d connected", vehicle + 1, *addr)

    def drop_connection(self, connection: Connection) -> None:
        if connection.closed:
            return
        connection.closed = True
        protocol = self.protocols[connection.vehicle]
        if connection in protocol.connections:
            protocol.connections.remove(connection)
        try:
            self._selector.unregister(connection.sock)
        except (KeyError, ValueError):
            pass
        connection.sock.close()

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
        channel: Connection = target
        for _ in range(64):  # bounded so one flooding peer cannot starve the clock
            try:
                if channel.tcp:
                    data = channel.sock.recv(65536)
                    if not data:
                        self.drop_connection(channel)
                        return
                else:
                    data, _addr = channel.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                if channel.tcp:
                    self.drop_connection(channel)
                return
            channel.feed(data)
            if channel.closed:
                return

    # ---- faults and links ---------------------------------------------------------------------------
    def link_passes(self, vehicle: int, kind: str) -> bool:
        if kind == GROUND and self.telemetry_radio is not None:
            loss = self.ground_loss[vehicle]
            if loss > 0 and self.world.rng.random() < loss:
                self.stats["radio_lost"] += 1
                return False
        if not self._faults_active:
            return True
        if self.world.link_down(vehicle, kind):
            return False
        loss_pct = self.world.loss_pct(vehicle, kind)
        return loss_pct <= 0 or self.world.rng.random() * 100.0 >= loss_pct

    def _on_params_changed(self) -> None:
        self._faults_active = self.world.any_link_fault()
        for protocol in self.protocols:
            protocol.on_params_changed()

    def _update_ground_loss(self) -> None:
        pos = self.world.state.pos_m
        horizontal = np.linalg.norm(pos[:, :2] - self._station_enu[:, :2], axis=1)
        height = self.world.heights_m()
        radio = self.telemetry_radio
        distance = np.hypot(horizontal, height - radio.ground_antenna_m)
        self.ground_loss = radio.frame_loss(distance, height)

    def flush(self) -> None:
        """Send everything queued on every connection."""
        while self.dirty:
            self.dirty.pop().flush()

    def set_param(self, vehicle: int, name: str, value: float) -> None:
        with self._lock:
            self.world.set_param(vehicle, name, value)

    def set_loss(self, vehicle: int, link: str, pct: float) -> None:
        """Drop pct % of packets both ways on the 'ground' or 'companion' link."""
        with self._lock:
            self.world.set_loss_pct(vehicle, link, pct)

    def set_link_down(self, vehicle: int, link: str, down: bool) -> None:
        with self._lock:
            self.world.set_link_down(vehicle, link, down)

    def set_gps_lost(self, vehicle: int, lost: bool) -> None:
        self.set_param(vehicle, "SIM_GPS_DISABLE", 1 if lost else 0)

    def set_battery_pct(self, vehicle: int, pct: float) -> None:
        self.set_param(vehicle, "SIM_BATT_PCT", pct)

    # ---- state --------------------------------------------------------------------------------------
    @property
    def t_s(self) -> float:
        return self.world.t_s

    def paced_t_s(self) -> float:
        """Simulated time now, for the run's shared clock: on the line the loop paces the world by while the world
        keeps up with it, the world's own time when it has fallen behind. The world moves in steps of dt_s (10 ms),
        so its time read at an arbitrary moment lags the line by up to a step: published that way, every reader's
        clock jumped by up to 10 simulated milliseconds at each re-read, and a delay line's deliveries with it."""
        wall0, sim0, speedup = self._pacing
        on_line = sim0 + (time.monotonic() - wall0) * speedup
        world_s = self.t_s
        now_s = on_line if world_s >= on_line - KEEPING_UP_S * speedup - self.config.dt_s else world_s
        self._paced_s = max(self._paced_s, now_s)  # a world that falls behind holds the clock, never takes it back
        return self._paced_s

    @property
    def homes(self) -> list[Home]:
        return self.world.homes

    def air_positions(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(simulated time, every vehicle's true earth-centred position (N, 3), its antenna's height above the
        ground (N,)), read at one step: what the radio between the vehicles sees."""
        with self._lock:
            return self.world.t_s, self.world.positions_ecef_m(), self.world.heights_m()

    def truth(self, vehicle: int) -> dict:
        """True state of one vehicle (for tests and tools): ENU about its home, geodetic, mode, armed."""
        with self._lock:
            return self.world.truth(vehicle)

    def batteries(self) -> tuple[float, list[dict]]:
        """(simulated time, each vehicle's flight pack: consumed_wh, soc, voltage_v), taken at one step."""
        with self._lock:
            s = self.world.state
            return self.world.t_s, [{"consumed_wh": float(wh), "soc": float(soc), "voltage_v": float(v)}
                                    for wh, soc, v in zip(s.consumed_wh, s.soc, s.voltage_v, strict=True)]

    # ---- the loop -----------------------------------------------------------------------------------
    def step_once(self) -> None:
        """Advance the world by one step and send what falls due (call with the lock held)."""
        for vehicle, kind, value in self.world.step(self.config.dt_s):
            self.protocols[vehicle].on_event(kind, value)
        if self.telemetry_radio is not None:
            self._update_ground_loss()
        self.stats["steps"] += 1
        for vehicle, msgid in self.streams.due(self.world.t_s):
            protocol = self.protocols[vehicle]
            protocol.send(protocol.build(msgid))

    def run(self) -> None:
        """Run until stop() (blocks the calling thread)."""
        dt = self.config.dt_s
        speedup = self._speedup
        wall0, sim0, speedup = self._pace_from_now(speedup)
        flushed_s = wall0
        while not self._stop.is_set():
            if self._speedup != speedup:  # a new pace from here on
                wall0, sim0, speedup = self._pace_from_now(self._speedup)
            with self._lock:
                target = sim0 + (time.monotonic() - wall0) * speedup
                steps = 0
                while self.t_s + dt <= target and steps < 20:
                    self.step_once()
                    steps += 1
                now = time.monotonic()
                if self.t_s + dt > target or now - flushed_s >= BEHIND_FLUSH_S:
                    self.flush()
                    flushed_s = now
                if self.signing is not None:
                    self.signing.save()  # at most once a second
                if target - self.t_s > 0.5 * speedup:  # fell behind by half a second: slip, don't spiral
                    self.stats["overruns"] += 1
                    wall0, sim0, speedup = self._pace_from_now(speedup)
                now = time.monotonic()
                for protocol in self.protocols:
                    protocol.poll_transfers(now)
            wait_s = min(max((self.t_s + dt - target) / speedup, 0.0), 0.02)
            for key, _ in self._selector.select(wait_s):
                with self._lock:
                    try:
                        self._read(*key.data)
                    except Exception:  # one bad socket event must not stop every vehicle
                        self.stats["io_errors"] += 1
                        log.exception("error reading %s", key.data[0])
                    self.flush()

    def _pace_from_now(self, speedup: float) -> tuple[float, float, float]:
        """A new pacing line from the world's time now (run()'s, and what paced_t_s reads)."""
        self._pacing = (time.monotonic(), self.t_s, speedup)
        return self._pacing

    def set_speedup(self, speedup: float) -> None:
        """Run at `speedup` from now on: the experiment runner lands the vehicles this way once nothing is recorded.
        SIM_SPEEDUP reports it."""
        with self._lock:
            self.world.params.values[:, self.world.params.index("SIM_SPEEDUP")] = speedup
            self._speedup = speedup

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
        if self.signing is not None:
            self.signing.save(force=True)

    def __enter__(self) -> Sitl:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
