"""Peer state over the vehicle network: the message every agent broadcasts, and the table of peers heard.

Pure: no sockets or clocks here; the agent passes datagrams and times in. A peer message is one UDP datagram:
the JSON body {"nac": "peer-state/1", "id", "role", "sysid", "lat_deg", "lon_deg", "alt_m", "vel_ned_mps",
"battery_pct", "t_s", "probe_port", "mpi_build"} (unknown positions are null), authenticated with the fleet key as
`NACS1 KEY_ID HMAC_SHA256_HEX\\n` + body, the HMAC over `KEY_ID\\n` + body (docs/security.md).

Everything that arrives is hostile until checked: the size before parsing, the signature before the body is
read, every field against its type and range, the sender's clock against a replay window, and the table against
its size. A datagram that fails any check raises PeerMessageError with a short reason the agent counts.
"""

from __future__ import annotations

import hmac
import json
import math
import re
from dataclasses import asdict, dataclass

from nac_onboard.errors import BadInput

PEER_PROTOCOL = "peer-state/1"
MAX_DATAGRAM_BYTES = 2048
SIGNED_MAGIC = b"NACS1 "
ID_PATTERN = re.compile(r"[A-Za-z0-9._-]{1,32}")
ROLES = ("master", "worker")
MAX_SPEED_MPS = 1000.0
MPI_BUILD_PATTERN = re.compile(r"[ -~]{0,160}")  # printable ASCII: it is printed when builds disagree
ALT_RANGE_M = (-1000.0, 100_000.0)


class PeerMessageError(BadInput):
    """A peer datagram that was refused; `reason` is a short name the agent counts by."""

    def __init__(self, reason: str, detail: str = ""):
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


@dataclass(frozen=True)
class FleetKey:
    """The secret every vehicle of a fleet shares, and the id that names it in each datagram."""

    key_id: str
    secret: bytes

    def __post_init__(self):
        if not ID_PATTERN.fullmatch(self.key_id):
            raise BadInput(f"fleet key id {self.key_id!r}: expected 1-32 letters, digits, '.', '_' or '-'")
        if len(self.secret) < 16:
            raise BadInput("fleet key: the secret must be at least 16 bytes")


@dataclass(frozen=True)
class PeerState:
    id: str
    role: str
    t_s: float  # the sender's clock when it sent this
    sysid: int = 0
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    vel_ned_mps: tuple | None = None
    battery_pct: int | None = None
    probe_port: int = 0  # its throughput server (0 = none)
    mpi_build: str = ""  # "MPICH 5.0.2 ch4:ucx ofi": every rank of a job needs the same ("": not reported)
    host: str = ""  # filled in by the receiver: the address the datagram came from

    def position(self) -> dict | None:
        if self.lat_deg is None or self.lon_deg is None or self.alt_m is None:
            return None
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_m": self.alt_m}


def _mac(key: FleetKey, body: bytes) -> bytes:
    return hmac.digest(key.secret, key.key_id.encode() + b"\n" + body, "sha256").hex().encode()  # C's fast path


def encode_peer_state(state: PeerState, key: FleetKey | None = None) -> bytes:
    fields = asdict(state)
    fields.pop("host")
    body = json.dumps({"nac": PEER_PROTOCOL, **fields}, separators=(",", ":"), allow_nan=False).encode()
    return body if key is None else sign(body, key)


def sign(body: bytes, key: FleetKey) -> bytes:
    """The datagram carrying body, authenticated with the fleet key."""
    return SIGNED_MAGIC + key.key_id.encode() + b" " + _mac(key, body) + b"\n" + body


def decode_peer_state(datagram: bytes, host: str, key: FleetKey | None, allow_unsigned: bool = False) -> PeerState:
    """The peer state in a datagram, or PeerMessageError: the signature is checked before the body is parsed."""
    if len(datagram) > MAX_DATAGRAM_BYTES:
        raise PeerMessageError("too_big", f"{len(datagram)} bytes")
    if datagram.startswith(SIGNED_MAGIC):
        header, newline, body = datagram.partition(b"\n")
        parts = header.split(b" ")
        if not newline or len(parts) != 3:
            raise PeerMessageError("bad_header")
        if key is None:
            raise PeerMessageError("unknown_key", "this agent has no fleet key")
        if parts[1] != key.key_id.encode():
            raise PeerMessageError("unknown_key", f"key id {parts[1][:32]!r}")
        if not hmac.compare_digest(parts[2], _mac(key, body)):
            raise PeerMessageError("bad_signature")
    elif key is not None and not allow_unsigned:
        raise PeerMessageError("unsigned")
    else:
        body = datagram
    return _check(_parse(body), host)


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a number JSON allows")


def _parse(body: bytes) -> dict:
    try:
        parsed = json.loads(body, parse_constant=_reject_constant)
    except (ValueError, UnicodeDecodeError, RecursionError):
        raise PeerMessageError("not_json") from None
    if not isinstance(parsed, dict) or parsed.get("nac") != PEER_PROTOCOL:
        raise PeerMessageError("not_peer_state", f"not a {PEER_PROTOCOL} message")
    return parsed


def _number(body: dict, key: str, low: float, high: float, *, optional: bool = False, integer: bool = False):
    value = body.get(key)
    if value is None and optional:
        return None
    if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
        raise PeerMessageError("schema", f"{key}: expected {'an integer' if integer else 'a number'}")
    try:
        if not (math.isfinite(value) and low <= value <= high):  # a huge int: OverflowError in isfinite
            raise PeerMessageError("schema", f"{key}: outside {low:g}..{high:g}")
    except OverflowError:
        raise PeerMessageError("schema", f"{key}: outside {low:g}..{high:g}") from None
    return int(value) if integer else float(value)


def _check(body: dict, host: str) -> PeerState:
    peer_id, role = body.get("id"), body.get("role")
    if not isinstance(peer_id, str) or not ID_PATTERN.fullmatch(peer_id):
        raise PeerMessageError("schema", "id: expected 1-32 letters, digits, '.', '_' or '-'")
    if role not in ROLES:
        raise PeerMessageError("schema", f"role: expected one of {', '.join(ROLES)}")
    mpi_build = body.get("mpi_build", "")
    if not isinstance(mpi_build, str) or not MPI_BUILD_PATTERN.fullmatch(mpi_build):
        raise PeerMessageError("schema", "mpi_build: expected up to 160 printable ASCII characters")
    vel = body.get("vel_ned_mps")
    if vel is not None:
        if not isinstance(vel, list) or len(vel) != 3:
            raise PeerMessageError("schema", "vel_ned_mps: expected [north, east, down]")
        vel = tuple(_number({"vel_ned_mps": v}, "vel_ned_mps", -MAX_SPEED_MPS, MAX_SPEED_MPS) for v in vel)
    return PeerState(
        id=peer_id, role=role, t_s=_number(body, "t_s", 0.0, 1e11),
        sysid=_number(body, "sysid", 0, 255, integer=True) if "sysid" in body else 0,
        lat_deg=_number(body, "lat_deg", -90.0, 90.0, optional=True),
        lon_deg=_number(body, "lon_deg", -180.0, 180.0, optional=True),
        alt_m=_number(body, "alt_m", *ALT_RANGE_M, optional=True), vel_ned_mps=vel,
        battery_pct=_number(body, "battery_pct", 0, 100, optional=True, integer=True),
        probe_port=_number(body, "probe_port", 0, 65535, integer=True) if "probe_port" in body else 0,
        mpi_build=mpi_build, host=host)


@dataclass(frozen=True)
class HeardPeer:
    """A peer as the table holds it: its last message, how long ago it came and whether the peer is lost."""

    state: PeerState
    age_s: float  # since its last message, to the millisecond
    lost: bool


@dataclass
class _Entry:
    state: PeerState
    heard_mono_s: float
    lost: bool = False


class PeerTable:
    """Peers by id with the age of their last message; a peer silent for timeout_s is lost until heard again and
    forgotten after forget_s. At most max_peers are kept: a forged flood of new ids cannot grow it."""

    def __init__(self, self_id: str, timeout_s: float, max_peers: int = 64, forget_s: float = 60.0,
                 replay_window_s: float | None = None):
        self.self_id, self.timeout_s = self_id, timeout_s
        self.max_peers, self.forget_s = max_peers, max(forget_s, timeout_s)
        self.replay_window_s = replay_window_s  # None: the sender's clock is not checked (unsigned fleets)
        self._entries: dict[str, _Entry] = {}

    def update(self, state: PeerState, now_mono_s: float, now_unix_s: float) -> bool:
        """Record a message; returns whether the peer is new or back after being lost (seen). Raises
        PeerMessageError for a replayed or stale message, or a new peer when the table is full."""
        if state.id == self.self_id:
            return False  # our own broadcast, looped back
        entry = self._entries.get(state.id)
        if self.replay_window_s is not None:
            if abs(state.t_s - now_unix_s) > self.replay_window_s:
                raise PeerMessageError("stale", f"{state.id}: sent at {state.t_s:.3f}, now {now_unix_s:.3f}")
            if entry is not None and state.t_s <= entry.state.t_s:
                raise PeerMessageError("replayed", f"{state.id}: not newer than its last message")
        if entry is None and len(self._entries) >= self.max_peers:
            raise PeerMessageError("table_full", f"{self.max_peers} peers already")
        seen = entry is None or entry.lost
        self._entries[state.id] = _Entry(state, now_mono_s)
        return seen

    def expire(self, now_mono_s: float) -> list[tuple[PeerState, float]]:
        """Peers that just went silent for longer than timeout_s, with how long they have been silent; peers
        silent past forget_s leave the table."""
        lost = []
        for peer_id, entry in list(self._entries.items()):
            silent_s = now_mono_s - entry.heard_mono_s
            if silent_s > self.forget_s:
                del self._entries[peer_id]
            elif not entry.lost and silent_s > self.timeout_s:
                entry.lost = True
                lost.append((entry.state, silent_s))
        return lost

    def live(self) -> list[PeerState]:
        return [e.state for e in self._entries.values() if not e.lost]

    def snapshot(self, now_mono_s: float) -> dict[str, HeardPeer]:
        """Every peer in the table by id: its last state, its age and whether it is lost."""
        return {peer_id: HeardPeer(e.state, round(now_mono_s - e.heard_mono_s, 3), e.lost)
                for peer_id, e in self._entries.items()}


class SenderMute:
    """Senders (address, port) that sent more than `bad_per_window` refused datagrams within `window_s` are muted
    for `mute_s`: their datagrams are counted and dropped before any check (under a flood, checking the signature
    of each is most of the agent's work). A fleet peer sends a few good datagrams a second and is never muted;
    one that an attacker impersonates from its own address loses at most `mute_s` of updates at a time. At most
    `max_senders` are tracked: a flood from ever new ports resets the table instead of growing it."""

    def __init__(self, bad_per_window: int = 50, window_s: float = 1.0, mute_s: float = 1.0,
                 max_senders: int = 1024):
        self.bad_per_window, self.window_s, self.mute_s = bad_per_window, window_s, mute_s
        self.max_senders = max_senders
        self._bad: dict[tuple, list[float]] = {}  # sender -> [window start, refused in it]
        self.muted_until: dict[tuple, float] = {}

    def muted(self, sender: tuple, now_s: float) -> bool:
        until = self.muted_until.get(sender)
        if until is None:
            return False
        if now_s < until:
            return True
        del self.muted_until[sender]
        return False

    def refused(self, sender: tuple, now_s: float) -> bool:
        """Note a refused datagram; True when this one mutes its sender."""
        entry = self._bad.get(sender)
        if entry is None or now_s - entry[0] >= self.window_s:
            if len(self._bad) >= self.max_senders:
                self._bad.clear()
            entry = self._bad[sender] = [now_s, 0]
        entry[1] += 1
        if entry[1] <= self.bad_per_window:
            return False
        if len(self.muted_until) >= self.max_senders:
            self.muted_until.clear()
        self.muted_until[sender] = now_s + self.mute_s
        del self._bad[sender]
        return True
