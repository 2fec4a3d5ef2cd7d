"""autopilot.peer (issue 34): who may be the autopilot on a listening link, checked when the config loads, with an
error naming the key and what was expected."""

import ipaddress

import pytest
from hypothesis import given
from hypothesis import strategies as st

from nac_onboard.agent.config import ConfigError, parse_agent_config
from nac_onboard.errors import BadInput
from nac_onboard.mavlink.client import PeerSpec, parse_peer

MINIMAL = {"vehicle": {"id": "uav1", "role": "worker"}, "peers": {"allow_unsigned": True}}


def config(**autopilot):
    return parse_agent_config({**MINIMAL, "autopilot": autopilot}, "agent.toml")


def test_peer_forms():
    assert parse_peer("", "autopilot.peer") == PeerSpec()
    assert parse_peer("192.168.144.10", "autopilot.peer") == PeerSpec("192.168.144.10", 0)
    assert parse_peer("127.0.0.1:14551", "autopilot.peer") == PeerSpec("127.0.0.1", 14551)
    assert config(uri="udpin:127.0.0.1:14551", peer="127.0.0.1:5000").autopilot.peer == "127.0.0.1:5000"
    assert config(uri="tcpin:0.0.0.0:5760", peer="192.168.144.10").autopilot.peer == "192.168.144.10"


@given(st.text(max_size=40))
def test_any_text_is_a_peer_or_a_clear_error(text):
    try:
        spec = parse_peer(text, "autopilot.peer")
    except BadInput as err:
        assert str(err).startswith("autopilot.peer: ") and "IPv4 address" in str(err)
        return
    if spec.host:  # what was taken is one unicast address and a port in range (0: any)
        address = ipaddress.IPv4Address(spec.host)
        assert not address.is_unspecified and not address.is_multicast and 0 <= spec.port <= 65535


@pytest.mark.parametrize("autopilot, message", [
    ({"uri": "udpin:0.0.0.0:14551", "peer": "uav-autopilot"}, "autopilot.peer: expected an IPv4 address"),
    ({"uri": "udpin:0.0.0.0:14551", "peer": "10.0.0.5:0"}, "autopilot.peer: expected an IPv4 address"),
    ({"uri": "udpin:0.0.0.0:14551", "peer": "0.0.0.0"}, "autopilot.peer: 0.0.0.0 is not one peer's address"),
    ({"uri": "udpin:0.0.0.0:14551", "peer": "224.0.0.1:14550"}, "is not one peer's address"),
    ({"uri": "serial:/dev/ttyTHS2:921600", "peer": "10.0.0.5"}, "autopilot.peer is only for a listening link"),
    ({"uri": "tcp:10.0.0.5:5760", "peer": "10.0.0.5"}, "autopilot.peer is only for a listening link"),
    ({"uri": "udpin:0.0.0.0:14551", "peer": 14550}, "autopilot.peer"),
])
def test_bad_peer_names_the_key(autopilot, message):
    with pytest.raises(ConfigError) as err:
        config(**autopilot)
    assert str(err.value).startswith("agent.toml: ") and message in str(err.value)
