"""Peer state over the vehicle network: the message every agent broadcasts, and the table of peers heard.

No sockets or clocks here; the agent passes datagrams and times in (the table reads and writes its freshness
file, below). A peer message is one UDP datagram: the JSON body {"nac": "peer-state/2", "id", "role", "boot", "seq",
"sysid", "lat_deg", "lon_deg", "alt_m", "vel_ned_mps", "battery_pct", "t_s", "probe_port", "mpi_build"} (unknown
positions and battery are null), authenticated with the fleet key as `NACS1 KEY_ID HMAC_SHA256_HEX\\n` + body, the
HMAC over `KEY_ID\\n` + body (docs/security.md). `boot` is random per start of the sending agent and `seq` its
monotonic clock in milliseconds since that start, strictly increasing: freshness is judged by the sender's own
sequence, not its wall clock (PeerTable). Version 1 (no boot, no seq) is refused by name: the fleet runs one version.

Everything that arrives is hostile until checked: the size before parsing, the signature before the body is
read, every field against its type and range, the sender's sequence against what we accepted before (and a new
boot against our clock), and the table against its size. A datagram that fails any check raises
PeerMessageError with a short reason the agent counts.
"""

from __future__ import annotations

import hmac
import json
import math
import os
import re
from dataclasses import asdict, dataclass
from pathlib import Path

from nac_onboard.errors import BadInput

PEER_PROTOCOL = "peer-state/2"
OLD_PROTOCOLS = ("peer-state/1",)
MAX_DATAGRAM_BYTES = 2048
SIGNED_MAGIC = b"NACS1 "
ID_PATTERN = re.compile(r"[A-Za-z0-9._-]{1,32}")
ROLES = ("master", "worker")
MAX_SPEED_MPS = 1000.0
MPI_BUILD_PATTERN = re.compile(r"[ -~]{0,160}")  # printable ASCII: it is printed when builds disagree
ALT_RANGE_M = (-1000.0, 100_000.0)
BOOT_PATTERN = re.compile(r"[0-9a-f]{16}")
MAX_SEQ = 2**53  # JSON's exact integers: 285,000 years of milliseconds
MAX_AHEAD_S = 2.0  # a sender's sequence may run this far ahead of the time we have seen pass since its anchor
MAX_DRIFT = 1e-3  # and this much more per second since (two monotonic clocks NTP slews by up to 500 ppm each)
MAX_BOOTS_PER_PEER = 4  # boots of one id tracked at once (a key holder's forged boot does not retire the real one)
FRESHNESS_VERSION = 1


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
    boot: str = ""  # 16 hex digits, random per start of the sending agent
    seq: int = 0  # the sender's monotonic clock in ms since that start, strictly increasing

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
    if isinstance(parsed, dict) and parsed.get("nac") in OLD_PROTOCOLS:
        raise PeerMessageError("old_version", f"{parsed['nac']}: this agent speaks {PEER_PROTOCOL} (update the fleet)")
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
    boot = body.get("boot")
    if not isinstance(boot, str) or not BOOT_PATTERN.fullmatch(boot):
        raise PeerMessageError("schema", "boot: expected 16 lowercase hex digits")
    battery = body.get("battery_pct")
    if battery == -1 and not isinstance(battery, bool):
        battery = None  # MAVLink's "unknown" (SYS_STATUS.battery_remaining = -1): unknown, not a reason to refuse
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
        battery_pct=_number({"battery_pct": battery}, "battery_pct", 0, 100, optional=True, integer=True),
        probe_port=_number(body, "probe_port", 0, 65535, integer=True) if "probe_port" in body else 0,
        mpi_build=mpi_build, host=host, boot=boot, seq=_number(body, "seq", 0, MAX_SEQ, integer=True))


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


@dataclass
class _Boot:
    """What we accepted from one boot of a peer: its last sequence, and the anchor that maps its sequence onto our
    monotonic clock (None until a message of it is accepted in this run of ours, or after the peer was forgotten)."""

    seq: int
    anchor_mono_s: float | None = None
    anchor_seq: int = 0
    last_mono_s: float = 0.0


class PeerStateFileError(BadInput):
    """The freshness file cannot be read or is not ours; the message names it."""


class PeerTable:
    """Peers by id with the age of their last message; a peer silent for timeout_s is lost until heard again and
    forgotten after forget_s. At most max_peers are kept: a forged flood of new ids cannot grow it.

    With replay_window_s set (signed fleets), a message must be fresh by its sender's own sequence:
      - a boot of the peer already heard in this run of ours: `seq` must be above the last accepted, and the time it
        claims to have passed since the boot's anchor (the first message of it we accepted) may run at most
        MAX_AHEAD_S (+ MAX_DRIFT per second since) ahead of the time that passed here, and at most replay_window_s
        behind. The sender's wall clock plays no part: a peer whose clock steps back keeps being heard, and a
        datagram stamped ahead (by `t_s` or by `seq`) is refused or leads by at most MAX_AHEAD_S (+ drift), so it
        cannot lock the peer out for longer.
      - a boot not heard in this run (a peer's restart, our restart, a peer forgotten): its `seq` must be above the
        last accepted for that boot if we know one (from the freshness file, so a datagram captured before our
        restart is refused after it), and its `t_s` within replay_window_s of our clock either way.
    A new boot does not retire the others (a forged one from a key holder does not silence the real one); at most
    MAX_BOOTS_PER_PEER are tracked per id, the least recently heard dropped first.
    """

    def __init__(self, self_id: str, timeout_s: float, max_peers: int = 64, forget_s: float = 60.0,
                 replay_window_s: float | None = None, freshness_path: str | Path | None = None):
        self.self_id, self.timeout_s = self_id, timeout_s
        self.max_peers, self.forget_s = max_peers, max(forget_s, timeout_s)
        self.replay_window_s = replay_window_s  # None: freshness is not checked (unsigned fleets)
        self._entries: dict[str, _Entry] = {}
        self._boots: dict[str, dict[str, _Boot]] = {}  # peer id -> boot -> what we accepted from it
        self.freshness_path = Path(freshness_path) if freshness_path else None
        self._dirty = False

    def update(self, state: PeerState, now_mono_s: float, now_unix_s: float) -> bool:
        """Record a message; returns whether the peer is new or back after being lost (seen). Raises
        PeerMessageError for a replayed, stale or too-far-ahead message, or a new peer when the table is full."""
        if state.id == self.self_id:
            return False  # our own broadcast, looped back
        entry = self._entries.get(state.id)
        if entry is None and len(self._entries) >= self.max_peers:
            raise PeerMessageError("table_full", f"{self.max_peers} peers already")
        if self.replay_window_s is not None:
            self._check_fresh(state, now_mono_s, now_unix_s)
        seen = entry is None or entry.lost
        self._entries[state.id] = _Entry(state, now_mono_s)
        return seen

    def _check_fresh(self, state: PeerState, now_mono_s: float, now_unix_s: float) -> None:
        window_s = self.replay_window_s
        boots = self._boots.get(state.id, {})
        boot = boots.get(state.boot)
        if boot is not None and state.seq <= boot.seq:
            raise PeerMessageError("replayed", f"{state.id}: seq {state.seq} not above {boot.seq} of boot {state.boot}")
        if boot is None or boot.anchor_mono_s is None:
            # nothing of this boot heard in this run of ours: only the sender's clock can vouch for it
            if not now_unix_s - window_s <= state.t_s <= now_unix_s + window_s:
                raise PeerMessageError("stale", f"{state.id}: a new boot sent at {state.t_s:.3f}, now "
                                                f"{now_unix_s:.3f} (window {window_s:g} s)")
            if boot is None:
                if len(boots) >= MAX_BOOTS_PER_PEER:
                    del boots[min(boots, key=lambda b: boots[b].last_mono_s)]
                if state.id not in self._boots and len(self._boots) >= 4 * self.max_peers:
                    del self._boots[min(self._boots, key=lambda p: max(
                        (b.last_mono_s for b in self._boots[p].values()), default=0.0))]
                boot = self._boots.setdefault(state.id, boots).setdefault(state.boot, _Boot(state.seq))
            boot.anchor_mono_s, boot.anchor_seq = now_mono_s, state.seq
        else:
            passed_s = now_mono_s - boot.anchor_mono_s
            claimed_s = (state.seq - boot.anchor_seq) / 1000.0
            drift_s = MAX_DRIFT * max(passed_s, 0.0)
            if claimed_s > passed_s + MAX_AHEAD_S + drift_s:
                raise PeerMessageError("ahead", f"{state.id}: seq {state.seq} is {claimed_s - passed_s:.3f} s "
                                                f"ahead of the time passed here (at most {MAX_AHEAD_S:g} s)")
            if claimed_s < passed_s - window_s - drift_s:
                raise PeerMessageError("stale", f"{state.id}: seq {state.seq} was sent {passed_s - claimed_s:.3f} "
                                                f"s ago by its own clock (window {window_s:g} s)")
        boot.seq, boot.last_mono_s = state.seq, now_mono_s
        self._dirty = True

    def expire(self, now_mono_s: float) -> list[tuple[PeerState, float]]:
        """Peers that just went silent for longer than timeout_s, with how long they have been silent; peers
        silent past forget_s leave the table (their boots keep their last sequence, but a message of them is then
        judged as a new boot's: a badly anchored boot cannot keep its peer out for longer)."""
        lost = []
        for peer_id, entry in list(self._entries.items()):
            silent_s = now_mono_s - entry.heard_mono_s
            if silent_s > self.forget_s:
                del self._entries[peer_id]
                for boot in self._boots.get(peer_id, {}).values():
                    boot.anchor_mono_s = None
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

    # ---- the freshness file: the last sequence accepted per peer and boot, so a restart of ours forgets nothing --
    def load(self) -> None:
        """Read the freshness file (a missing one is an empty start); PeerStateFileError names a bad one."""
        path = self.freshness_path
        if path is None or not path.exists():
            return
        try:
            if not path.is_file():
                raise PeerStateFileError(f"peer freshness file {path}: not a regular file")
            with open(path, "rb") as f:
                data = json.loads(f.read(1 << 20), parse_constant=_reject_constant)
            if not isinstance(data, dict) or data.get("version") != FRESHNESS_VERSION:
                raise ValueError(f"expected version {FRESHNESS_VERSION}")
            boots: dict[str, dict[str, _Boot]] = {}
            for peer_id, seqs in data["peers"].items():
                if not ID_PATTERN.fullmatch(peer_id) or not isinstance(seqs, dict):
                    raise ValueError(f"peer {peer_id[:40]!r}")
                for boot, seq in list(seqs.items())[:MAX_BOOTS_PER_PEER]:
                    if not BOOT_PATTERN.fullmatch(boot) or isinstance(seq, bool) or not isinstance(seq, int) \
                            or not 0 <= seq <= MAX_SEQ:
                        raise ValueError(f"peer {peer_id}: boot {boot[:20]!r}")
                    boots.setdefault(peer_id, {})[boot] = _Boot(seq)
                if len(boots) >= 4 * self.max_peers:
                    break
        except OSError as err:
            raise PeerStateFileError(f"cannot read peer freshness file {path}: {err.strerror}") from None
        except (ValueError, KeyError, TypeError, AttributeError, UnicodeDecodeError, RecursionError) as err:
            raise PeerStateFileError(f"peer freshness file {path}: not one this agent wrote ({err})") from None
        self._boots = boots

    def save(self) -> None:
        """Write the freshness file if anything was accepted since the last save (atomically: a crash leaves the
        old or the new one). Raises OSError."""
        path = self.freshness_path
        if path is None or not self._dirty:
            return
        peers = {peer_id: {boot: b.seq for boot, b in boots.items()} for peer_id, boots in self._boots.items()}
        data = json.dumps({"version": FRESHNESS_VERSION, "peers": peers}, separators=(",", ":")).encode()
        temporary = path.with_name(path.name + ".tmp")
        with open(temporary, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(temporary, path)
        self._dirty = False


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
