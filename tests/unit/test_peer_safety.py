"""Peer state from the Wi-Fi is hostile until checked: datagrams that killed the agent, forged and replayed
state, floods of ids and answers too big for a datagram (issue: safe on a real network)."""

import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from nac_onboard.agent.config import MIN_PASSPHRASE_CHARS, ConfigError, parse_agent_config
from nac_onboard.agent.peers import (
    MAX_AHEAD_S,
    MAX_DATAGRAM_BYTES,
    FleetKey,
    PeerMessageError,
    PeerState,
    PeerStateFileError,
    PeerTable,
    SenderMute,
    decode_peer_state,
    encode_peer_state,
)
from nac_onboard.agent.state_feed import MAX_ANSWER_BYTES, encode_answer
from nac_onboard.mavlink.client import TelemetryState

KEY = FleetKey("lab", bytes(range(32)))
NOW = 1.8e9
BOOT = "0123456789abcdef"
GOOD = {"nac": "peer-state/2", "id": "w1", "role": "worker", "boot": BOOT, "seq": 1, "t_s": NOW, "sysid": 2,
        "lat_deg": 47.0, "lon_deg": 8.0, "alt_m": 500.0, "vel_ned_mps": [0.0, 0.0, 0.0], "battery_pct": 90,
        "probe_port": 5201}
FUZZ_EXAMPLES = 400


def body(**changes) -> bytes:
    return json.dumps({**GOOD, **changes}).encode()


@pytest.mark.parametrize("datagram", [
    body(battery_pct=1e400),  # json reads 1e400 as inf: an OverflowError once
    b'{"nac":"peer-state/2","id":"w1","role":"worker","boot":"0123456789abcdef","seq":1,"t_s":1,"lat_deg":'
    + b"9" * 400 + b"}",
    b"[" * 2000,  # RecursionError once
    body(lat_deg=float("nan")), body(alt_m=float("inf")), body(probe_port=-1), body(probe_port=70000),
    body(id="x" * 33), body(id="a b"), body(id=""), body(role="boss"), body(sysid=True), body(sysid=300),
    body(vel_ned_mps=[1, 2]), body(vel_ned_mps=["a", 0, 0]), body(t_s="soon"), b"\xff\xfe",
    body(mpi_build=7), body(mpi_build="MPICH\n\x1b[2J"), body(mpi_build="M" * 161),  # it is printed
    body(boot=None), body(boot="0123456789ABCDEF"), body(boot="xyz"), body(boot=7), body(seq=-1),
    body(seq=2**53 + 1), body(seq=1.5), body(seq="1"), body(battery_pct=-2), body(battery_pct=101),
    b"{" + b'"a":1,' * 400 + b'"nac":"peer-state/2"}',  # too big
])
def test_datagrams_that_crashed_the_agent_are_refused_by_name(datagram):
    with pytest.raises(PeerMessageError) as err:
        decode_peer_state(datagram, "10.0.0.66", None, allow_unsigned=True)
    assert err.value.reason in {"schema", "not_json", "not_peer_state", "too_big"}


def test_signed_state_round_trips_and_forgeries_are_refused():
    state = PeerState("w1", "worker", NOW, lat_deg=47.0, lon_deg=8.0, alt_m=500.0, boot=BOOT)
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
    built = PeerState("w1", "worker", NOW, mpi_build="MPICH 5.0.2 ch4:ucx ofi", boot=BOOT)
    assert decode_peer_state(encode_peer_state(built, KEY), "10.0.0.2", KEY).mpi_build == "MPICH 5.0.2 ch4:ucx ofi"


def test_replayed_and_stale_signed_state_is_refused():
    table = PeerTable("m", timeout_s=3.0, replay_window_s=30.0)
    first = PeerState("w1", "worker", NOW, boot=BOOT, seq=1000)
    assert table.update(first, 0.0, NOW) is True
    with pytest.raises(PeerMessageError, match="replayed"):
        table.update(first, 1.0, NOW + 1)  # the same message captured and sent again
    with pytest.raises(PeerMessageError, match="stale"):  # a boot never heard, dated far from our clock
        table.update(PeerState("w1", "worker", NOW + 3600, boot="f" * 16, seq=5), 1.0, NOW + 1)
    with pytest.raises(PeerMessageError, match="ahead"):  # its own sequence far ahead of the time passed here
        table.update(PeerState("w1", "worker", NOW + 1, boot=BOOT, seq=1000 + 3600_000), 1.0, NOW + 1)
    assert table.update(PeerState("w1", "worker", NOW + 1, boot=BOOT, seq=2000), 1.0, NOW + 1) is False


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


# ---- freshness by the sender's own sequence (issue 34: peer state) --------------------------------------------
PERIOD_S = 0.5  # the genuine peer's sending period in these simulations


def genuine(k: int, wall_offset_s: float = 0.0, boot: str = BOOT) -> PeerState:
    """The genuine peer's k-th message: its sequence is its monotonic milliseconds, its wall clock may be off."""
    return PeerState("w1", "worker", NOW + k * PERIOD_S + wall_offset_s, boot=boot, seq=int(k * PERIOD_S * 1000) + 1)


def accepted(table: PeerTable, state: PeerState, now_mono_s: float, now_unix_s: float) -> bool:
    try:
        table.update(state, now_mono_s, now_unix_s)
        return True
    except PeerMessageError:
        return False


@settings(max_examples=200, deadline=None)
@given(ahead_s=st.floats(0.0, 1e7), seq_lead_s=st.floats(0.0, 1e7), when=st.integers(1, 30),
       delay_s=st.floats(0.0, 0.3))
def test_a_future_stamped_datagram_cannot_lock_the_genuine_peer_out(ahead_s, seq_lead_s, when, delay_s):
    """A key holder's (or the peer's own, before its clock stepped back) datagram dated ahead, by its wall clock
    and by its sequence: refused, or it leads the genuine peer by at most MAX_AHEAD_S (+ drift); the genuine peer is
    heard again within that, never for ahead_s."""
    table = PeerTable("m", timeout_s=3.0, replay_window_s=30.0)
    refused_after = []
    for k in range(60):
        now = k * PERIOD_S + delay_s * (k % 3) / 3  # receiver's clocks: delays vary a little per datagram
        if k == when:
            state = genuine(k)
            forged = PeerState("w1", "worker", state.t_s + ahead_s, boot=BOOT,
                               seq=min(state.seq + int(seq_lead_s * 1000), 2**53))
            accepted(table, forged, now, NOW + now)
        ok = accepted(table, genuine(k), now, NOW + now)
        assert ok or k >= when, "every message before the forgery is taken"
        if not ok:
            refused_after.append(k)
    assert len(refused_after) <= (MAX_AHEAD_S + 1.0) / PERIOD_S + 1, refused_after
    assert table.live()[0].seq == genuine(59).seq, "the genuine peer is heard at the end"


@settings(max_examples=200, deadline=None)
@given(step_s=st.floats(-1e6, -0.001), at=st.integers(1, 40))
def test_a_peer_whose_clock_steps_back_keeps_being_heard(step_s, at):
    """An NTP correction at the peer moves its wall clock back by any amount: every message is still taken, in
    order, because within a boot only its sequence counts."""
    table = PeerTable("m", timeout_s=3.0, replay_window_s=30.0)
    for k in range(50):
        state = genuine(k, wall_offset_s=step_s if k >= at else 0.0)
        table.update(state, k * PERIOD_S, NOW + k * PERIOD_S)  # raises if refused
    with pytest.raises(PeerMessageError, match="replayed"):
        table.update(genuine(20, step_s), 50 * PERIOD_S, NOW + 50 * PERIOD_S)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(heard=st.integers(2, 40), replayed=st.data(), downtime_s=st.floats(0.0, 25.0))
def test_a_datagram_replayed_after_the_receiver_restarts_is_refused(tmp_path, heard, replayed, downtime_s):
    """The last sequence accepted per peer outlives a restart of ours (the freshness file): any datagram heard
    before it, replayed after it, is refused, even one still inside replay_window_s by the wall clock; the peer's
    next message is taken."""
    path = tmp_path / f"fresh-{heard}-{downtime_s}.json"
    before = PeerTable("m", timeout_s=3.0, replay_window_s=30.0, freshness_path=path)
    for k in range(heard):
        before.update(genuine(k), k * PERIOD_S, NOW + k * PERIOD_S)
    before.save()
    after = PeerTable("m", timeout_s=3.0, replay_window_s=30.0, freshness_path=path)  # our restart: new clocks
    after.load()
    k = replayed.draw(st.integers(0, heard - 1))
    now_unix = NOW + heard * PERIOD_S + downtime_s
    with pytest.raises(PeerMessageError, match="replayed"):
        after.update(genuine(k), 0.0, now_unix)
    assert after.update(genuine(heard + int(downtime_s / PERIOD_S)), 0.0, now_unix) is True
    path.unlink()


def test_without_the_freshness_file_a_new_boot_must_be_fresh_by_our_clock(tmp_path):
    """Nothing known of a peer (no file, or ours could not be read): a datagram older than replay_window_s by our
    clock is refused; a bad freshness file is named, not a traceback."""
    table = PeerTable("m", timeout_s=3.0, replay_window_s=10.0, freshness_path=tmp_path / "none.json")
    table.load()
    with pytest.raises(PeerMessageError, match="stale"):
        table.update(genuine(0), 0.0, NOW + 15.0)
    assert table.update(genuine(0), 0.0, NOW + 5.0) is True
    for text in ("{", "[]", '{"version": 1, "peers": {"w 1": {}}}', '{"version": 1, "peers": {"w1": {"x": 1}}}',
                 '{"version": 2, "peers": {}}', '{"version": 1, "peers": {"w1": {"0123456789abcdef": -1}}}'):
        bad = tmp_path / "bad.json"
        bad.write_text(text)
        with pytest.raises(PeerStateFileError, match="bad.json"):
            PeerTable("m", 3.0, replay_window_s=10.0, freshness_path=bad).load()


def test_a_forged_new_boot_does_not_retire_the_genuine_one():
    """A key holder announcing a new boot of w1 does not silence the real w1 (boots are tracked side by side)."""
    table = PeerTable("m", timeout_s=3.0, replay_window_s=30.0)
    table.update(genuine(0), 0.0, NOW)
    table.update(genuine(1, boot="f" * 16), 0.5, NOW + 0.5)
    assert table.update(genuine(2), 1.0, NOW + 1.0) is False


def test_version_1_messages_are_refused_by_name():
    with pytest.raises(PeerMessageError) as err:
        decode_peer_state(json.dumps({**GOOD, "nac": "peer-state/1"}).encode(), "10.0.0.2", None, True)
    assert err.value.reason == "old_version" and "peer-state/2" in str(err.value)


# ---- MAVLink's "unknown" is unknown, never a reason to refuse a vehicle --------------------------------------
@settings(max_examples=300, deadline=None)
@given(remaining=st.integers(-128, 127), voltage_mv=st.integers(0, 65535))
def test_unknown_battery_is_unknown_and_the_vehicle_stays_in_the_fleet(remaining, voltage_mv):
    """SYS_STATUS as an autopilot sends it (battery_remaining -1 and voltage_battery UINT16_MAX mean unknown): the
    telemetry state holds a percentage or None, and the peer message built from it is taken by every peer."""
    state = TelemetryState(sysid=1)
    state.apply(mavlink.MAVLink_sys_status_message(0, 0, 0, 0, voltage_mv, -1, remaining, 0, 0, 0, 0, 0, 0), 0.0)
    assert state.battery_pct == (remaining if 0 <= remaining <= 100 else None)
    assert state.voltage_v == (None if voltage_mv == 65535 else voltage_mv / 1000)
    own = PeerState("w1", "worker", NOW, battery_pct=state.battery_pct, boot=BOOT, seq=1)
    assert decode_peer_state(encode_peer_state(own, KEY), "10.0.0.2", KEY).battery_pct == state.battery_pct


def test_a_peer_sending_mavlinks_unknown_battery_is_taken_with_the_battery_unknown():
    assert decode_peer_state(body(battery_pct=-1), "10.0.0.2", None, allow_unsigned=True).battery_pct is None
    assert decode_peer_state(body(battery_pct=None), "10.0.0.2", None, allow_unsigned=True).battery_pct is None


# ---- a weak fleet passphrase is refused at config load -------------------------------------------------------
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(passphrase=st.text(st.characters(min_codepoint=33, max_codepoint=0x2FFF), min_size=1,
                          max_size=MIN_PASSPHRASE_CHARS - 1))
def test_a_weak_fleet_passphrase_is_refused_naming_the_field_and_the_minimum(tmp_path, passphrase):
    key = tmp_path / "fleet.key"
    key.write_text(passphrase + "\n")
    with pytest.raises(ConfigError) as err:
        parse_agent_config({"vehicle": {"id": "w1", "role": "worker"}, "peers": {"key_file": str(key)}}, "a.toml")
    message = str(err.value)
    assert message.startswith("a.toml: peers.key_file: ") and f"at least {MIN_PASSPHRASE_CHARS}" in message


@pytest.mark.parametrize("text", ["correct horse battery staple", "0123456789abcdef" * 4, "x" * MIN_PASSPHRASE_CHARS])
def test_a_long_passphrase_or_a_real_key_is_taken(tmp_path, text):
    key = tmp_path / "fleet.key"
    key.write_text(text + "\n")
    config = parse_agent_config({"vehicle": {"id": "w1", "role": "worker"}, "peers": {"key_file": str(key)}}, "a.toml")
    assert config.fleet_key is not None and len(config.fleet_key.secret) == 32
