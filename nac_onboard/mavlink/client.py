"""MAVLink client used by the ground station, the agent and the demo (the one module here importing pymavlink).

Endpoints are URIs: udpin:HOST:PORT (listen, as QGroundControl does), udpout:HOST:PORT (send first),
tcp:HOST:PORT, serial:DEVICE:BAUD. The environment variable NAC_MAVLINK_URI overrides the default. One client
holds one or more links and tracks every vehicle heard on them, by system id.
"""

from __future__ import annotations

import errno
import hashlib
import ipaddress
import logging
import os
import select
import socket
import time
from collections import deque
from dataclasses import dataclass, field

from missions.model import MavCmd
from nac_onboard.address import parse_host_port
from nac_onboard.errors import BadInput, OperationFailed
from nac_onboard.mavlink.dialect import COPTER_MODES, M, enum_name, mavutil
from nac_onboard.mavlink.frames import INCOMPAT_SIGNED, frame_msgid, frame_source, split_frames
from nac_onboard.mavlink.mission_transfer import MissionTransfer
from nac_onboard.mavlink.signing import SigningState

log = logging.getLogger(__name__)
DEFAULT_URI = "udpin:0.0.0.0:14550"
LANDED_STATES = {M.MAV_LANDED_STATE_UNDEFINED: "unknown", M.MAV_LANDED_STATE_ON_GROUND: "on ground",
                 M.MAV_LANDED_STATE_IN_AIR: "in air", M.MAV_LANDED_STATE_TAKEOFF: "taking off",
                 M.MAV_LANDED_STATE_LANDING: "landing"}
HEARTBEAT_PERIOD_S = 1.0
TEXTS_KEPT = 20  # a vehicle's last STATUSTEXTs, for the reasons of a refusal
WORDS_WAIT_S = 0.3  # after a refusal, how long a STATUSTEXT that follows its ACK is waited for
UINT16_UNKNOWN = 65535  # SYS_STATUS.voltage_battery: "not sent by the autopilot"
#: What TelemetryState and the client's own operations (commands, mission transfer) read.
CLIENT_MESSAGES = frozenset({
    "HEARTBEAT", "GLOBAL_POSITION_INT", "ATTITUDE", "SYS_STATUS", "EXTENDED_SYS_STATE", "MISSION_CURRENT",
    "MISSION_ITEM_REACHED", "COMMAND_ACK", "MISSION_COUNT", "MISSION_REQUEST", "MISSION_REQUEST_INT",
    "MISSION_ITEM_INT", "MISSION_ACK", "STATUSTEXT"})


class LinkError(OperationFailed):
    """The link could not be opened or stayed silent; the message says which endpoint and what was expected."""


class LinkClosed(LinkError):
    """The other end closed a stream link (TCP); the link must be opened again."""


class CommandError(OperationFailed):
    def __init__(self, command: int, result: int, sysid: int, said: list[str] | tuple = ()):
        self.command, self.result, self.said = command, result, list(said)
        name = enum_name("MAV_RESULT", result)
        cmd = enum_name("MAV_CMD", command)
        super().__init__(f"vehicle {sysid} refused {cmd}: {name}{words(said)}")


def words(said) -> str:
    """What a vehicle said about a refusal (its STATUSTEXTs), for the end of a sentence."""
    return "; it said: " + " / ".join(f'"{text}"' for text in said) if said else ""


def printable_text(text) -> str:
    """A STATUSTEXT's text as a terminal may show it: anything from the network, so no control characters."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    return "".join(c if c.isprintable() else "?" for c in str(text).rstrip("\0")).strip()[:200]





#: URI scheme -> pymavlink options; the device string is the URI itself for network links.
_NETWORK_SCHEMES = {"udpin": {}, "udpout": {}, "tcpin": {},
                    "tcp": {"retries": 0}}  # fail fast: callers that want to wait retry on their own schedule


#: A refused datagram or connection costs one recvfrom_into (or accept) and a compare; at most this many are taken
#: per read, so a flood cannot hold the caller's loop (10 ms of a 50,000/s flood).
REFUSED_PER_READ = 512
MAX_DATAGRAM_BYTES = 65535


@dataclass(frozen=True)
class PeerSpec:
    """Who may be the other end of a listening link (udpin:, tcpin:): HOST (an IP address) and PORT, or HOST with
    any port (port 0), or nobody named (host ""): the first sender that speaks a valid MAVLink frame (signed with
    our key when signing is on), then locked to it. Everyone else is refused and counted. A peer taken as the first
    that spoke is released only when its owner says the peer went silent (release())."""

    host: str = ""
    port: int = 0

    def __str__(self) -> str:
        return "first sender" if not self.host else f"{self.host}:{self.port}" if self.port else self.host


def parse_peer(text: str, what: str) -> PeerSpec:
    """PeerSpec from "" (the first that speaks), "HOST" or "HOST:PORT" with HOST an IPv4 address; BadInput naming
    `what` otherwise."""
    text = str(text).strip()
    if not text:
        return PeerSpec()
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = text, ""
    expected = f"{what}: expected an IPv4 address, optionally with :PORT (1-65535), got {text!r}"
    try:
        address = ipaddress.IPv4Address(host)
    except ValueError:
        raise BadInput(expected) from None
    if port and not (port.isdigit() and 1 <= int(port) <= 65535):
        raise BadInput(expected)
    if address.is_unspecified or address.is_multicast or address == ipaddress.IPv4Address("255.255.255.255"):
        raise BadInput(f"{what}: {host} is not one peer's address; {expected[len(what) + 2:]}")
    return PeerSpec(str(address), int(port) if port else 0)


class _PeerLock:
    """What both one-peer links share: the rule for who is taken, the refusal counters."""

    def _init_lock(self, peer: PeerSpec, key: bytes | None) -> None:
        self.peer_spec, self.key, self._configured = peer, key, peer
        self.refused = 0  # datagrams or connections from anyone but the peer, since the link opened
        self.last_refused_from: tuple[str, int] | None = None
        self._checker = M.MAVLink(None)  # CRC only: decoding with the link's own parser would change its state

    def release(self) -> None:
        """Forget a peer taken as the first that spoke (the autopilot went silent: it may come back from another
        port, as a restarted SITL does); a configured HOST:PORT is kept."""
        self.peer_spec = self._configured
        if hasattr(self, "peer") and not (self._configured.host and self._configured.port):
            self.peer = None

    def _refuse(self, sender) -> None:
        self.refused += 1
        self.last_refused_from = sender

    def _host_allowed(self, sender) -> bool:
        spec = self.peer_spec
        return not spec.host or (sender[0] == spec.host and (not spec.port or sender[1] == spec.port))

    def _speaks_mavlink(self, data) -> bool:
        """Whether data holds a frame with a valid CRC (and, with a key, a valid signature)."""
        for frame in split_frames(data)[0]:
            if self.key is not None:
                if not frame[2] & INCOMPAT_SIGNED or frame[0] != 0xFD or \
                        hashlib.sha256(self.key + frame[:-6]).digest()[:6] != frame[-6:]:
                    continue
            try:  # the checker has no key: it checks the CRC and leaves signatures (and their state) alone
                self._checker.decode(bytearray(frame))
            except M.MAVError:
                continue
            except Exception:  # noqa: BLE001 - a hostile frame pymavlink cannot unpack
                continue
            return True
        return False


class OnePeerUdp(mavutil.mavudp, _PeerLock):
    """udpin: a listening UDP link with one peer. pymavlink's own udpin answers every address that ever sent it a
    datagram (and takes their frames as the autopilot's); this one takes frames only from its peer and sends only
    to it. A refused datagram is read into one buffer and dropped before any decoding."""

    def __init__(self, address: str, peer: PeerSpec, key: bytes | None, **kwargs):
        super().__init__(address, input=True, **kwargs)
        self._init_lock(peer, key)
        self.peer: tuple[str, int] | None = (peer.host, peer.port) if peer.host and peer.port else None
        self._buffer = bytearray(MAX_DATAGRAM_BYTES)
        self._view = memoryview(self._buffer)

    def recv(self, n=None):
        receive, view = self.port.recvfrom_into, self._view
        for _ in range(REFUSED_PER_READ):
            try:
                size, sender = receive(self._buffer)
            except (BlockingIOError, InterruptedError):
                return b""
            except OSError:  # an ICMP error from an earlier send: nothing to read now
                return b""
            if sender == self.peer:
                return bytes(view[:size])
            if self.peer is None and self._host_allowed(sender) and self._speaks_mavlink(bytes(view[:size])):
                self.peer = sender
                return bytes(view[:size])
            self._refuse(sender)
        return b""

    def write(self, buf):
        if self.peer is None:
            return  # nobody to answer yet: never anyone else
        try:
            self.port.sendto(buf, self.peer)
        except OSError:
            pass


class OnePeerTcpIn(mavutil.mavtcpin, _PeerLock):
    """tcpin: one connection at a time, from the peer's host (the configured one, else the first that connected);
    every other connection is accepted and closed at once (so none waits in the backlog), and counted."""

    def __init__(self, address: str, peer: PeerSpec, key: bytes | None, **kwargs):
        super().__init__(address, **kwargs)
        self._init_lock(PeerSpec(peer.host), key)  # a TCP client's port is ephemeral: its host is the peer

    def recv(self, n=None):
        for _ in range(REFUSED_PER_READ):
            try:
                conn, sender = self.listen.accept()
            except OSError:
                break
            if self.port is None and self._host_allowed(sender):
                if not self.peer_spec.host:
                    self.peer_spec = PeerSpec(sender[0])  # locked to the first host that connected
                conn.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)
                conn.setblocking(False)
                mavutil.set_close_on_exec(conn.fileno())
                self.port, self.fd = conn, conn.fileno()
            else:
                conn.close()
                self._refuse(sender)
        if self.port is None:
            return b""
        try:
            data = self.port.recv(n or MAX_DATAGRAM_BYTES)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError:
            data = b""
        if not data:  # the peer closed: wait for it to connect again (from its host)
            self.port.close()
            self.port, self.fd = None, self.listen.fileno()
        return data

    def write(self, buf):
        if self.port is None:
            return
        try:
            self.port.send(buf)
        except OSError as err:
            if err.errno in (errno.EPIPE, errno.ECONNRESET):
                self.port.close()
                self.port, self.fd = None, self.listen.fileno()


def mavutil_device(uri: str) -> tuple[str, dict]:
    """Map a NAC endpoint URI to pymavlink's device string and options; BadInput for anything else."""
    scheme, _, rest = uri.partition(":")
    expected = "expected udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT or serial:DEVICE:BAUD"
    if scheme in _NETWORK_SCHEMES:
        try:
            parse_host_port(rest, f"endpoint {uri!r}", allow_port_zero=scheme in ("udpin", "tcpin"))
        except BadInput as err:
            raise BadInput(f"{err}; {expected}") from None
        return uri, dict(_NETWORK_SCHEMES[scheme])
    if scheme == "serial":
        device, _, baud = rest.rpartition(":")
        if device and baud.isdigit() and int(baud) > 0:
            return device, {"baud": int(baud)}
    raise BadInput(f"endpoint {uri!r} not understood: {expected}")


@dataclass
class TelemetryState:
    """What a vehicle last told us about itself."""

    sysid: int
    link: int = 0  # index of the link it was heard on
    autopilot: int = 0
    mode: str = "?"
    armed: bool = False
    lat_deg: float = float("nan")
    lon_deg: float = float("nan")
    alt_m: float = float("nan")
    rel_alt_m: float = float("nan")
    vel_ned_mps: tuple = (0.0, 0.0, 0.0)
    roll_deg: float = 0.0
    pitch_deg: float = 0.0
    yaw_deg: float = 0.0
    battery_pct: int | None = None  # None: unknown (MAVLink's battery_remaining = -1, or not heard yet)
    voltage_v: float | None = None  # None: unknown (MAVLink's voltage_battery = UINT16_MAX, or not heard yet)
    landed: str = "unknown"
    time_boot_ms: int = -1  # the autopilot's clock at the last position (GLOBAL_POSITION_INT)
    mission_seq: int = 0
    mission_total: int = 0
    mission_state: int = 0
    last_heartbeat_s: float = 0.0
    reached: list = field(default_factory=list)
    texts: deque = field(default_factory=lambda: deque(maxlen=TEXTS_KEPT))  # (monotonic s, severity, text)

    @property
    def ground_speed_mps(self) -> float:
        return (self.vel_ned_mps[0] ** 2 + self.vel_ned_mps[1] ** 2) ** 0.5

    def link_age_s(self, now_s: float | None = None) -> float:
        return (time.monotonic() if now_s is None else now_s) - self.last_heartbeat_s

    def apply(self, msg, now_s: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            self.last_heartbeat_s = now_s
            self.autopilot = msg.autopilot
            self.armed = bool(msg.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
            if msg.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                self.mode = mavutil.mode_mapping_acm.get(msg.custom_mode, str(msg.custom_mode))
        elif kind == "GLOBAL_POSITION_INT":
            self.time_boot_ms = msg.time_boot_ms
            self.lat_deg, self.lon_deg = msg.lat / 1e7, msg.lon / 1e7
            self.alt_m, self.rel_alt_m = msg.alt / 1000, msg.relative_alt / 1000
            self.vel_ned_mps = (msg.vx / 100, msg.vy / 100, msg.vz / 100)
        elif kind == "ATTITUDE":
            self.roll_deg, self.pitch_deg, self.yaw_deg = (v * 57.29577951308232 for v in
                                                           (msg.roll, msg.pitch, msg.yaw))
        elif kind == "SYS_STATUS":
            # MAVLink's "unknown" (-1, UINT16_MAX) and anything outside the field's range are unknown, not numbers
            remaining = msg.battery_remaining
            self.battery_pct = remaining if 0 <= remaining <= 100 else None
            self.voltage_v = msg.voltage_battery / 1000 if msg.voltage_battery != UINT16_UNKNOWN else None
        elif kind == "EXTENDED_SYS_STATE":
            self.landed = LANDED_STATES.get(msg.landed_state, "unknown")
        elif kind == "MISSION_CURRENT":
            self.mission_seq = msg.seq
            self.mission_total = getattr(msg, "total", 0)
            self.mission_state = getattr(msg, "mission_state", 0)
        elif kind == "MISSION_ITEM_REACHED":
            self.reached.append(msg.seq)
        elif kind == "STATUSTEXT":
            self.texts.append((now_s, int(msg.severity), printable_text(msg.text)))

    def said_since(self, since_s: float) -> list[str]:
        return [text for at_s, _, text in self.texts if at_s >= since_s and text]


class RawFrame:
    """A frame passed through undecoded: enough of the message interface for logging and routing."""

    __slots__ = ("_frame", "_msgid")

    def __init__(self, frame: bytes, msgid: int):
        self._frame, self._msgid = frame, msgid

    def get_type(self) -> str:
        known = M.mavlink_map.get(self._msgid)
        return known.msgname if known is not None else f"UNKNOWN_{self._msgid}"

    def get_msgbuf(self) -> bytes:
        return self._frame

    def get_srcSystem(self) -> int:  # noqa: N802 (pymavlink's name)
        return frame_source(self._frame)[0]

    def get_srcComponent(self) -> int:  # noqa: N802
        return frame_source(self._frame)[1]


class Link:
    def __init__(self, uri: str, index: int, source_system: int, source_component: int,
                 signing: SigningState | None, mav_type: int = M.MAV_TYPE_GCS, one_peer: PeerSpec | None = None):
        """one_peer: a listening link (udpin:, tcpin:) takes frames from that one peer only (OnePeerUdp,
        OnePeerTcpIn); None keeps pymavlink's listen-to-everyone (ground tools hearing several vehicles)."""
        self.uri, self.index, self.mav_type = uri, index, mav_type
        device, options = mavutil_device(uri)
        scheme, _, address = uri.partition(":")
        key = signing.key if signing is not None else None
        try:
            if one_peer is not None and scheme == "udpin":
                self.conn = OnePeerUdp(address, one_peer, key, source_system=source_system,
                                       source_component=source_component)
            elif one_peer is not None and scheme == "tcpin":
                self.conn = OnePeerTcpIn(address, one_peer, key, source_system=source_system,
                                         source_component=source_component)
            else:
                self.conn = mavutil.mavlink_connection(device, source_system=source_system,
                                                       source_component=source_component, **options)
        except OSError as err:
            raise LinkError(f"cannot open {uri}: {err.strerror or err}") from None
        self.signing_key = signing.key if signing is not None else None
        self.stream = not uri.startswith("udp")  # frames may straddle reads
        self.pending = bytearray()
        if uri.startswith("tcp"):
            # pymavlink prints and returns nothing forever on a closed TCP socket unless told to reconnect itself.
            self.conn.handle_eof = self.conn.handle_disconnect = self._closed
        if signing is not None:
            self.conn.setup_signing(signing.key, sign_outgoing=True)
            signing.install(self.conn.mav)
        self.last_heartbeat_sent_s = 0.0
        self.bad_signature_frames = 0
        self.signed_frames_unverified = 0  # signed frames heard while we have no key

    def fileno(self) -> int:
        return self.conn.fd if getattr(self.conn, "fd", None) is not None else self.conn.port.fileno()

    @property
    def refused(self) -> int:
        """Datagrams or connections refused from others than the one peer (0 for links without one)."""
        return getattr(self.conn, "refused", 0)

    def release_peer(self) -> None:
        """The peer went silent: a listening one-peer link takes the next that speaks (within autopilot.peer)."""
        if hasattr(self.conn, "release"):
            self.conn.release()

    @property
    def peer(self) -> str:
        """HOST:PORT the link answers ("" while nobody has spoken, or for links without one peer)."""
        peer = getattr(self.conn, "peer", None)
        return f"{peer[0]}:{peer[1]}" if peer else ""

    def read_filtered(self, wanted_ids: frozenset) -> list:
        """Everything waiting on the link, decoding only the message ids in wanted_ids; other frames come back
        as RawFrame (pymavlink's decoding is most of a busy link's cost, and most frames are only logged)."""
        out = []
        while True:
            data = self.conn.recv(65535)
            if not data:
                return out
            if isinstance(data, str):
                data = data.encode("latin-1")
            if self.stream:
                self.pending += data
                frames, used, _ = split_frames(self.pending)
                del self.pending[:used]
            else:
                frames = split_frames(data)[0]  # a datagram holds whole frames: resynchronise on each
            for frame in frames:
                msgid = frame_msgid(frame)
                if msgid not in wanted_ids:
                    out.append(RawFrame(frame, msgid))
                    continue
                try:
                    out.append(self.conn.mav.decode(bytearray(frame)))
                except M.MAVError as err:
                    out.append(M.MAVLink_bad_data(bytearray(frame), err.message))

    def write_frame(self, frame: bytes) -> None:
        """Send a frame someone else built (routed) on this link, unchanged."""
        self.conn.write(frame)

    def _closed(self):
        raise LinkClosed(f"{self.uri}: the other end closed the connection")

    def heartbeat(self, now_s: float) -> None:
        if now_s - self.last_heartbeat_sent_s >= HEARTBEAT_PERIOD_S:
            self.last_heartbeat_sent_s = now_s
            try:
                self.conn.mav.heartbeat_send(self.mav_type, M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE)
            except OSError:
                pass  # nobody to send to yet (a listening link before the first packet)

    def close(self) -> None:
        self.conn.close()


class MavlinkClient(MissionTransfer):
    """Several links, every vehicle heard on them; operations address a vehicle by system id."""

    def __init__(self, uris: list[str] | str | None = None, sysid: int | None = None, signing_key: bytes | None = None,
                 source_system: int = 255, source_component: int = M.MAV_COMP_ID_MISSIONPLANNER,
                 mav_type: int = M.MAV_TYPE_GCS, decode_only: set[str] | None = None,
                 signing_state_file: str | None = None, one_peer: PeerSpec | None = None):
        """decode_only: message names to decode (plus what the client itself needs); every other frame is
        returned as a RawFrame. None decodes everything. one_peer: listening links take one peer only (Link)."""
        if uris is None or uris == []:
            uris = [os.environ.get("NAC_MAVLINK_URI", DEFAULT_URI)]
        elif isinstance(uris, str):
            uris = [uris]
        self.links: list[Link] = []
        # one signing state for every link: the timestamps of one key on this machine (kept beside the key file)
        self.signing = SigningState(signing_key, signing_state_file) if signing_key is not None else None
        self._link_args = (source_system, source_component, self.signing, mav_type, one_peer)
        try:
            for k, uri in enumerate(uris):
                self.links.append(Link(uri, k, *self._link_args))
        except LinkError:
            self.close()
            raise
        self.wanted_ids = None if decode_only is None else frozenset(
            getattr(M, f"MAVLINK_MSG_ID_{name}") for name in set(decode_only) | CLIENT_MESSAGES)
        self.sysid = sysid  # default target; None = the first vehicle heard
        self.vehicles: dict[int, TelemetryState] = {}
        self._inbox: deque = deque()  # received, not yet offered to recv()
        self.command_sent_s = 0.0  # monotonic time of the last command sent: its refusal's words came after it

    @property
    def conn(self):
        return self.links[0].conn

    def close(self) -> None:
        for link in self.links:
            link.close()
        if self.signing is not None:
            self.signing.save(force=True)

    def reopen(self, index: int = 0) -> Link:
        """Close and open a link again (a serial device that came back, a TCP peer that restarted)."""
        old = self.links[index]
        old.close()
        self.links[index] = Link(old.uri, index, *self._link_args)
        return self.links[index]

    def tap_sent(self, callback) -> None:
        """Call callback(frame_bytes) for every frame this client sends (the agent's .tlog)."""
        for link in self.links:
            link.conn.mav.set_send_callback(lambda msg: callback(msg.get_msgbuf()))

    def request_streams(self, rate_hz: float, sysid: int | None = None) -> None:
        """Ask the autopilot to stream all telemetry at rate_hz (REQUEST_DATA_STREAM, as MAVProxy's SR does)."""
        target = self.sysid if sysid is None else sysid
        self._link_for(target).mav.request_data_stream_send(target, 1, M.MAV_DATA_STREAM_ALL,
                                                            max(1, round(rate_hz)), 1)

    def __enter__(self) -> MavlinkClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- receiving --------------------------------------------------------------------------------------
    def _drain(self, link: Link, now_s: float):
        if self.wanted_ids is None:
            messages = iter(lambda: link.conn.recv_match(blocking=False), None)
        else:
            messages = link.read_filtered(self.wanted_ids)
        for msg in messages:
            if isinstance(msg, RawFrame):
                yield link, msg
                continue
            kind = msg.get_type()
            if kind == "BAD_DATA":
                if "signature" in str(getattr(msg, "reason", "")).lower():
                    link.bad_signature_frames += 1
                continue
            if link.signing_key is None and msg.get_header().incompat_flags & INCOMPAT_SIGNED:
                link.signed_frames_unverified += 1
            sysid = msg.get_srcSystem()
            if msg.get_srcComponent() == 1 or kind == "HEARTBEAT" and msg.type != M.MAV_TYPE_GCS:
                state = self.vehicles.get(sysid)
                if state is None and kind == "HEARTBEAT":
                    state = self.vehicles[sysid] = TelemetryState(sysid, link.index)
                if state is not None:
                    state.apply(msg, now_s)
            yield link, msg

    def poll(self, timeout_s: float) -> list:
        """Wait up to timeout_s for traffic on any link; returns the messages that arrived."""
        ready, _, _ = select.select(self.links, [], [], max(timeout_s, 0.0))
        now = time.monotonic()
        out = []
        for link in self.links:
            link.heartbeat(now)
            out.extend(msg for _, msg in self._drain(link, now))
        return out

    def recv(self, types, timeout_s: float, predicate=lambda m: True, sysid: int | None = None):
        """The next message of `types` from the vehicle matching predicate, or None after timeout_s."""
        target = self.sysid if sysid is None else sysid
        types = {types} if isinstance(types, str) else set(types)
        deadline = time.monotonic() + timeout_s
        while True:
            self._inbox.extend(self.poll(0.0))
            while self._inbox:  # like recv_match, what does not match is consumed and dropped
                msg = self._inbox.popleft()
                if (msg.get_type() in types and (target is None or msg.get_srcSystem() == target)
                        and predicate(msg)):
                    return msg
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            select.select(self.links, [], [], min(left, 0.1))

    def wait_heartbeat(self, timeout_s: float = 5.0, sysid: int | None = None):
        target = self.sysid if sysid is None else sysid
        hb = self.recv("HEARTBEAT", timeout_s, lambda m: m.type != M.MAV_TYPE_GCS, sysid=target)
        if hb is None:
            raise LinkError(self.silence_reason(target, timeout_s))
        if self.sysid is None:
            self.sysid = hb.get_srcSystem()
        link = self.links[self.vehicles[hb.get_srcSystem()].link]
        link.conn.target_system, link.conn.target_component = hb.get_srcSystem(), 1
        return hb

    def silence_reason(self, sysid: int | None, timeout_s: float) -> str:
        who = "any vehicle" if sysid is None else f"vehicle {sysid}"
        where = ", ".join(link.uri for link in self.links)
        text = f"no heartbeat from {who} on {where} within {timeout_s:g} s"
        if any(link.bad_signature_frames for link in self.links):
            text += " (frames arrived with an invalid signature: the signing key differs from the vehicle's)"
        return text

    def signing_hint(self) -> str:
        if any(link.signed_frames_unverified for link in self.links):
            return " The vehicle signs its messages: it needs our messages signed too (--signing-key-file)."
        return ""

    def _link_for(self, sysid: int):
        state = self.vehicles.get(sysid)
        return self.links[state.link if state else 0].conn

    # ---- commands ---------------------------------------------------------------------------------------
    def command(self, command: int, *params: float, timeout_s: float = 1.5, retries: int = 3,
                sysid: int | None = None) -> int:
        """Send COMMAND_LONG until its COMMAND_ACK arrives (confirmation counts retries); returns MAV_RESULT."""
        target = self.sysid if sysid is None else sysid
        self.command_sent_s = time.monotonic()
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        for confirmation in range(retries):
            self._link_for(target).mav.command_long_send(target, 1, command, confirmation, *p)
            ack = self.recv("COMMAND_ACK", timeout_s,
                            lambda m: m.command == command and m.result != M.MAV_RESULT_IN_PROGRESS, sysid=target)
            if ack is not None:
                return ack.result
        raise LinkError(f"no answer from vehicle {target} to {enum_name('MAV_CMD', command)} after {retries} "
                        f"tries of {timeout_s:g} s.{self.signing_hint()}")

    def command_ok(self, command: int, *params: float, sysid: int | None = None, **kwargs) -> None:
        target = self.sysid if sysid is None else sysid
        result = self.command(command, *params, sysid=target, **kwargs)
        if result != M.MAV_RESULT_ACCEPTED:
            raise CommandError(command, result, target, self.said_since(target, self.command_sent_s))

    def said_since(self, sysid: int, since_s: float, wait_s: float = WORDS_WAIT_S) -> list[str]:
        """The vehicle's STATUSTEXTs since since_s (monotonic): ArduPilot says why before or just after an ACK that
        refuses, so a refusal with nothing said yet waits up to wait_s for it."""
        deadline = time.monotonic() + wait_s
        while True:
            state = self.vehicles.get(sysid)
            said = state.said_since(since_s) if state else []
            if said or time.monotonic() >= deadline:
                return said
            self._inbox.extend(self.poll(min(0.05, max(deadline - time.monotonic(), 0.0))))

    def set_mode(self, name: str, sysid: int | None = None) -> int:
        if name not in COPTER_MODES:
            raise ValueError(f"unknown mode {name!r}; known: {', '.join(sorted(COPTER_MODES))}")
        return self.command(MavCmd.DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES[name],
                            sysid=sysid)


class VehicleClient(MavlinkClient):
    """One link, one vehicle: the shape the demo and simple tools need."""

    def __init__(self, uri: str | None = None, sysid: int = 1, source_system: int = 255,
                 source_component: int = M.MAV_COMP_ID_MISSIONPLANNER, signing_key: bytes | None = None):
        super().__init__(uri, sysid=sysid, signing_key=signing_key, source_system=source_system,
                         source_component=source_component)
