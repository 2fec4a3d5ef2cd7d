"""The agent's local state feed: the compute job asks, the agent answers with where everyone is.

One UDP datagram each way on the companion itself (default 127.0.0.1:47200). The answer is JSON:
{"t_s", "self": {id, role, lat_deg, lon_deg, alt_m, vel_ned_mps, link_up, ...}, "peers": {id: {..., age_s, lost}}}.
"""

from __future__ import annotations

import json
import socket

from missions.geo import distance_m
from nac_onboard.address import parse_host_port
from nac_onboard.errors import OperationFailed

REQUEST = b'{"get":"state"}'
MAX_ANSWER_BYTES = 65000


class StateFeedError(OperationFailed):
    pass


def fetch_state(address: str = "127.0.0.1:47200", timeout_s: float = 1.0) -> dict:
    """Ask the agent at address (HOST:PORT) for the current positions; raises StateFeedError on no answer."""
    host, port = parse_host_port(address, "state feed")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.settimeout(timeout_s)
        try:
            sock.sendto(REQUEST, (host, port))
            data, _ = sock.recvfrom(MAX_ANSWER_BYTES)
        except (TimeoutError, OSError) as err:
            raise StateFeedError(f"no answer from the agent's state feed at {address} within {timeout_s:g} s "
                                 f"({err.strerror or err}); is nac-onboard agent running?") from None
    try:
        return json.loads(data)
    except ValueError:
        raise StateFeedError(f"the state feed at {address} answered something that is not JSON") from None


def encode_answer(state: dict) -> bytes:
    data = json.dumps(state, separators=(",", ":")).encode()
    if len(data) > MAX_ANSWER_BYTES:
        raise ValueError(f"state answer of {len(data)} bytes does not fit one datagram")
    return data


def position_of(state: dict, vehicle: str) -> dict | None:
    """A vehicle's entry in a state-feed answer (the agent itself or a peer); None if unknown."""
    if state["self"]["id"] == vehicle:
        return state["self"]
    return state["peers"].get(vehicle)


def distance_between(state: dict, a: str, b: str) -> float | None:
    """Distance between two vehicles of a state-feed answer; None when either position is unknown."""
    pa, pb = position_of(state, a), position_of(state, b)
    return None if pa is None or pb is None else distance_m(pa, pb)
