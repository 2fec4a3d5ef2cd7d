"""The agent's local state feed: the compute job asks, the agent answers with where everyone is.

One UDP datagram each way on the companion itself (default 127.0.0.1:47200). The answer is JSON:
{"t_s", "self": {id, role, lat_deg, lon_deg, alt_m, vel_ned_mps, link_up, ...}, "peers": {id: {..., boot, age_s,
lost}},
"probes": {id: {bits_per_second, age_s}}} (probes: only on a vehicle that probes, each peer's latest).
The agent hands a typed AgentSnapshot (nac_onboard.agent.snapshot); this module alone writes it as JSON, and
`position_of`/`distance_between` read the JSON answer back, for the processes that ask.
"""

from __future__ import annotations

import contextlib
import json
import socket
from dataclasses import asdict

from missions.geo import distance_m
from nac_onboard.address import parse_host_port
from nac_onboard.agent.snapshot import AgentSnapshot
from nac_onboard.errors import OperationFailed
from nac_onboard.flight_log import json_finite

REQUEST = b'{"get":"state"}'  # the only request answered: anything else is dropped, unanswered
MAX_ANSWER_BYTES = 16384  # an answer always fits one datagram; peers that do not fit are left out and counted


class StateFeedError(OperationFailed):
    pass


def fetch_state(address: str = "127.0.0.1:47200", timeout_s: float = 1.0,
                sock: socket.socket | None = None) -> dict:
    """Ask the agent at address (HOST:PORT) for the current positions; raises StateFeedError on no answer.
    sock: a UDP socket to ask from, kept by the caller (one made in another network namespace); answers to
    earlier questions still queued on it are dropped first."""
    host, port = parse_host_port(address, "state feed")
    with contextlib.nullcontext(sock) if sock is not None else socket.socket(socket.AF_INET, socket.SOCK_DGRAM) \
            as asking:
        try:
            if sock is not None:
                asking.setblocking(False)
                with contextlib.suppress(BlockingIOError):
                    while True:
                        asking.recv(65535)
            asking.settimeout(timeout_s)
            asking.sendto(REQUEST, (host, port))
            data, _ = asking.recvfrom(65535)
        except (TimeoutError, OSError) as err:
            raise StateFeedError(f"no answer from the agent's state feed at {address} within {timeout_s:g} s "
                                 f"({err.strerror or err}); is nac-onboard agent running?") from None
    try:
        return json.loads(data)
    except ValueError:
        raise StateFeedError(f"the state feed at {address} answered something that is not JSON") from None


def answer_of(snapshot: AgentSnapshot) -> dict:
    """The answer's JSON object: "self" is the own state, each peer its last message with age_s and lost (without
    its seq: that is the peer messages' freshness, not the feed's)."""
    peers = {p.state.id: {**_without_freshness(asdict(p.state)), "age_s": p.age_s, "lost": p.lost}
             for p in snapshot.peers}
    answer = {"t_s": snapshot.t_s, "self": asdict(snapshot.own), "peers": peers}
    if snapshot.probes:  # only a vehicle that probes (the master) has them
        answer["probes"] = {p.peer: {"bits_per_second": p.bits_per_second, "age_s": p.age_s} for p in snapshot.probes}
    return answer


def _without_freshness(fields: dict) -> dict:
    del fields["seq"]  # boot stays: which start of the peer's agent this is (a supervisor sees a reboot by it)
    return fields


def encode_snapshot(snapshot: AgentSnapshot) -> bytes:
    """The datagram answering a state request."""
    return encode_answer(answer_of(snapshot))


def encode_answer(state: dict) -> bytes:
    """Standard JSON (no NaN: unknown values are null) that fits MAX_ANSWER_BYTES: the peers heard longest ago
    are left out first, and "peers_left_out" says how many."""
    peers = dict(state.get("peers", {}))
    left_out = 0
    while True:
        answer = {**state, "peers": peers}
        if left_out:
            answer["peers_left_out"] = left_out
        data = json.dumps(json_finite(answer), separators=(",", ":"), allow_nan=False).encode()
        if len(data) <= MAX_ANSWER_BYTES or not peers:
            return data
        oldest = max(peers, key=lambda pid: (bool(peers[pid].get("lost")), peers[pid].get("age_s") or 0.0))
        del peers[oldest]
        left_out += 1


def position_of(state: dict, vehicle: str) -> dict | None:
    """A vehicle's entry in a state-feed answer (the agent itself or a peer); None if unknown."""
    if state["self"]["id"] == vehicle:
        return state["self"]
    return state["peers"].get(vehicle)


def distance_between(state: dict, a: str, b: str) -> float | None:
    """Distance between two vehicles of a state-feed answer; None when either position is unknown."""
    pa, pb = position_of(state, a), position_of(state, b)
    return None if pa is None or pb is None else distance_m(pa, pb)
