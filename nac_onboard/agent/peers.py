"""Peer state over the vehicle network: the message every agent broadcasts, and the table of peers heard.

Pure: no sockets or clocks here; the agent passes datagrams and monotonic times in. A peer message is one UDP
datagram of JSON: {"nac": "peer-state/1", "id", "role", "sysid", "lat_deg", "lon_deg", "alt_m", "vel_ned_mps",
"battery_pct", "t_s", "probe_port"}. Unknown positions are null.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass

from nac_onboard.errors import BadInput

PEER_PROTOCOL = "peer-state/1"
MAX_DATAGRAM_BYTES = 2048


class PeerMessageError(BadInput):
    pass


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
    host: str = ""  # filled in by the receiver: the address the datagram came from

    def position(self) -> dict | None:
        if self.lat_deg is None or self.lon_deg is None or self.alt_m is None:
            return None
        return {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_m": self.alt_m}


def encode_peer_state(state: PeerState) -> bytes:
    body = {"nac": PEER_PROTOCOL, **asdict(state)}
    body.pop("host")
    return json.dumps(body, separators=(",", ":")).encode()


def decode_peer_state(datagram: bytes, host: str) -> PeerState:
    try:
        body = json.loads(datagram)
    except (ValueError, UnicodeDecodeError):
        raise PeerMessageError("not JSON") from None
    if not isinstance(body, dict) or body.get("nac") != PEER_PROTOCOL:
        raise PeerMessageError(f"not a {PEER_PROTOCOL} message")
    try:
        vel = body.get("vel_ned_mps")
        return PeerState(
            id=str(body["id"]), role=str(body["role"]), t_s=float(body["t_s"]), sysid=int(body.get("sysid", 0)),
            lat_deg=_opt_float(body.get("lat_deg")), lon_deg=_opt_float(body.get("lon_deg")),
            alt_m=_opt_float(body.get("alt_m")), vel_ned_mps=tuple(float(v) for v in vel) if vel else None,
            battery_pct=None if body.get("battery_pct") is None else int(body["battery_pct"]),
            probe_port=int(body.get("probe_port", 0)), host=host)
    except (KeyError, TypeError, ValueError) as err:
        raise PeerMessageError(f"bad field: {err}") from None


def _opt_float(value) -> float | None:
    return None if value is None else float(value)


@dataclass
class _Entry:
    state: PeerState
    heard_mono_s: float
    lost: bool = False


class PeerTable:
    """Peers by id with the age of their last message; a peer silent for timeout_s is lost until heard again."""

    def __init__(self, self_id: str, timeout_s: float):
        self.self_id, self.timeout_s = self_id, timeout_s
        self._entries: dict[str, _Entry] = {}

    def update(self, state: PeerState, now_mono_s: float) -> str | None:
        """Record a message; returns "peer_seen" when the peer is new or back after being lost."""
        if state.id == self.self_id:
            return None  # our own broadcast, looped back
        entry = self._entries.get(state.id)
        event = "peer_seen" if entry is None or entry.lost else None
        self._entries[state.id] = _Entry(state, now_mono_s)
        return event

    def expire(self, now_mono_s: float) -> list[tuple[PeerState, float]]:
        """Peers that just went silent for longer than timeout_s, with how long they have been silent."""
        lost = []
        for entry in self._entries.values():
            silent_s = now_mono_s - entry.heard_mono_s
            if not entry.lost and silent_s > self.timeout_s:
                entry.lost = True
                lost.append((entry.state, silent_s))
        return lost

    def live(self) -> list[PeerState]:
        return [e.state for e in self._entries.values() if not e.lost]

    def snapshot(self, now_mono_s: float) -> dict[str, dict]:
        """Every peer ever heard: its last state, age_s and whether it is lost."""
        out = {}
        for peer_id, e in self._entries.items():
            record = asdict(e.state)
            record.update(age_s=round(now_mono_s - e.heard_mono_s, 3), lost=e.lost)
            out[peer_id] = record
        return out
