"""Peer state from the Wi-Fi is hostile until checked: datagrams that killed the agent, forged and replayed
state, floods of ids and answers too big for a datagram (issue: safe on a real network)."""

import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nac_onboard.agent.peers import (
    MAX_DATAGRAM_BYTES,
    FleetKey,
    PeerMessageError,
    PeerState,
    PeerTable,
    SenderMute,
    decode_peer_state,
    encode_peer_state,
)
from nac_onboard.agent.state_feed import MAX_ANSWER_BYTES, encode_answer

KEY = FleetKey("lab", bytes(range(32)))
NOW = 1.8e9
GOOD = {"nac": "peer-state/1", "id": "w1", "role": "worker", "t_s": NOW, "sysid": 2, "lat_deg": 47.0,
        "lon_deg": 8.0, "alt_m": 500.0, "vel_ned_mps": [0.0, 0.0, 0.0], "battery_pct": 90, "probe_port": 5201}
FUZZ_EXAMPLES = 400


def body(**changes) -> bytes:
    return json.dumps({**GOOD, **changes}).encode()


@pytest.mark.parametrize("datagram", [
    body(battery_pct=1e400),  # json reads 1e400 as inf: an OverflowError once
    b'{"nac":"peer-state/1","id":"w1","role":"worker","t_s":1,"lat_deg":' + b"9" * 400 + b"}",
    b"[" * 2000,  # RecursionError once
    body(lat_deg=float("nan")), body(alt_m=float("inf")), body(probe_port=-1), body(probe_port=70000),
    body(id="x" * 33), body(id="a b"), body(id=""), body(role="boss"), body(sysid=True), body(sysid=300),
    body(vel_ned_mps=[1, 2]), body(vel_ned_mps=["a", 0, 0]), body(t_s="soon"), b"\xff\xfe",
    body(mpi_build=7), body(mpi_build="MPICH\n\x1b[2J"), body(mpi_build="M" * 161),  # it is printed
    b"{" + b'"a":1,' * 400 + b'"nac":"peer-state/1"}',  # too big
])
def test_datagrams_that_crashed_the_agent_are_refused_by_name(datagram):
    with pytest.raises(PeerMessageError) as err:
        decode_peer_state(datagram, "10.0.0.66", None, allow_unsigned=True)
    assert err.value.reason in {"schema", "not_json", "not_peer_state", "too_big"}


def test_signed_state_round_trips_and_forgeries_are_refused():
    state = PeerState("w1", "worker", NOW, lat_deg=47.0, lon_deg=8.0, alt_m=500.0)
    signed = encode_peer_state(state, KEY)
    assert decode_peer_state(signed, "10.0.0.2", KEY).lat_deg == 47.0
    tampered = signed.replace(b'"lat_deg":47.0', b'"lat_deg":48.0')
    reasons = {}
    for name, datagram, key in [("tampered", tampered, KEY), ("unsigned", encode_peer_state(state), KEY),
                                ("other fleet", encode_peer_state(state, FleetKey("lab", b"x" * 32)), KEY),
                                ("other key id", encode_peer_state(state, FleetKey("lab2", bytes(range(32)))), KEY),
                                ("no key here", signed, None)]:
        with pytest.raises(PeerMessageError) as err:
            decode_peer_state(datagram, "10.0.0.66", key)
        reasons[name] = err.value.reason
    assert reasons == {"tampered": "bad_signature", "unsigned": "unsigned", "other fleet": "bad_signature",
                       "other key id": "unknown_key", "no key here": "unknown_key"}
    assert decode_peer_state(encode_peer_state(state), "10.0.0.3", KEY, allow_unsigned=True).id == "w1"
    built = PeerState("w1", "worker", NOW, mpi_build="MPICH 5.0.2 ch4:ucx ofi")
    assert decode_peer_state(encode_peer_state(built, KEY), "10.0.0.2", KEY).mpi_build == "MPICH 5.0.2 ch4:ucx ofi"


def test_replayed_and_stale_signed_state_is_refused():
    table = PeerTable("m", timeout_s=3.0, replay_window_s=30.0)
    first = PeerState("w1", "worker", NOW)
    assert table.update(first, 0.0, NOW) is True
    with pytest.raises(PeerMessageError, match="replayed"):
        table.update(first, 1.0, NOW + 1)  # the same message captured and sent again
    with pytest.raises(PeerMessageError, match="stale"):
        table.update(PeerState("w1", "worker", NOW + 3600), 1.0, NOW + 1)  # dated far ahead: would lock out
    assert table.update(PeerState("w1", "worker", NOW + 1), 1.0, NOW + 1) is False


def test_a_flood_of_forged_ids_cannot_grow_the_table_and_silent_peers_are_forgotten():
    table = PeerTable("m", timeout_s=1.0, max_peers=64, forget_s=10.0)
    refused = 0
    for k in range(50_000):
        try:
            table.update(PeerState(f"forged{k}", "worker", NOW), 0.0, NOW)
        except PeerMessageError as err:
            assert err.reason == "table_full"
            refused += 1
    assert len(table.snapshot(0.0)) == 64 and refused == 50_000 - 64
    table.expire(11.0)
    assert table.snapshot(11.0) == {}
    assert table.update(PeerState("w1", "worker", NOW), 11.0, NOW) is True


def test_the_state_feed_answer_always_fits_a_datagram_and_is_standard_json():
    peers = {f"uav{k:03d}": {"id": f"uav{k:03d}", "lat_deg": 47.0, "lon_deg": float("nan"), "age_s": k / 10,
                              "lost": k % 7 == 0, "note": "x" * 100} for k in range(500)}
    data = encode_answer({"t_s": NOW, "self": {"id": "m", "alt_m": float("inf")}, "peers": peers})
    assert len(data) <= MAX_ANSWER_BYTES
    answer = json.loads(data, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert answer["self"]["alt_m"] is None and answer["peers_left_out"] + len(answer["peers"]) == 500
    assert not any(p["lost"] for p in answer["peers"].values()), "lost peers are left out first"


@settings(max_examples=FUZZ_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.one_of(st.binary(max_size=MAX_DATAGRAM_BYTES + 10),
                 st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=40),
                              lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=12), inner,
                                                                                           max_size=8),
                              max_leaves=30).map(lambda v: json.dumps(v).encode()),
                 st.fixed_dictionaries({k: st.one_of(st.just(v), st.integers(), st.floats(), st.text(max_size=40),
                                                     st.none()) for k, v in GOOD.items()})
                 .map(lambda d: json.dumps(d).encode())))
def test_fuzzed_datagrams_are_refused_or_valid_never_an_exception(datagram):
    for key, allow in ((None, True), (KEY, False)):
        try:
            state = decode_peer_state(datagram, "10.0.0.66", key, allow)
        except PeerMessageError:
            continue
        assert -90 <= (state.lat_deg or 0) <= 90 and 0 <= state.probe_port <= 65535



def test_a_sender_of_refused_datagrams_is_muted_for_a_while_and_others_are_not():
    mute = SenderMute(bad_per_window=3, window_s=1.0, mute_s=2.0, max_senders=4)
    attacker, peer = ("10.0.0.9", 5000), ("10.0.0.2", 14560)
    assert [mute.refused(attacker, 0.1 * k) for k in range(4)] == [False, False, False, True]
    assert mute.muted(attacker, 1.0) and not mute.muted(peer, 1.0)
    assert not mute.muted(attacker, 2.31), "muted for mute_s, then heard again"
    assert not any(mute.refused(peer, 10.0 * k) for k in range(10)), "one refusal now and then never mutes"
    for port in range(100):  # a flood from ever new ports resets the table instead of growing it
        mute.refused(("10.0.0.9", port), 50.0)
    assert len(mute._bad) <= 4 and len(mute.muted_until) <= 4
