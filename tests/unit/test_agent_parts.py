"""The agent's pure parts: config checking, peer messages and table, flight-log reading and writing, distances."""

import dataclasses
import json
import math
import shutil
import socket
import struct
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from missions.geo import Home, distance_m, enu_to_lla
from nac_onboard.agent.config import ConfigError, load_agent_config, parse_agent_config
from nac_onboard.agent.daemon import TextLimiter
from nac_onboard.agent.peers import PeerMessageError, PeerState, PeerTable, decode_peer_state, encode_peer_state
from nac_onboard.agent.snapshot import AgentSnapshot, OwnState, ProbeResult
from nac_onboard.agent.state_feed import distance_between, encode_snapshot
from nac_onboard.agent.systemd_notify import SystemdNotifier
from nac_onboard.compute import positions
from nac_onboard.compute.positions import FeedDistances
from nac_onboard.flight_log import JsonlLog, TlogWriter, read_jsonl
from nac_onboard.records import kinds

MINIMAL = {"vehicle": {"id": "uav1", "role": "worker"}, "peers": {"allow_unsigned": True}}


def test_minimal_config_takes_the_jetson_defaults():
    config = parse_agent_config(MINIMAL)
    assert config.autopilot.uri == "serial:/dev/ttyTHS2:921600"
    assert config.log.dir == "/var/log/nac" and config.log.telemetry_hz == 10.0
    assert config.throughput.port == 5201 and not config.throughput.probe


@pytest.mark.parametrize("data, message", [
    ({}, "missing [vehicle]"),
    ({"vehicle": {"id": "uav1"}}, "[vehicle] needs role"),
    ({"vehicle": {"id": "uav1", "role": "boss"}}, "vehicle.role must be one of master, worker"),
    ({"vehicle": {"id": "uav 1", "role": "worker"}}, "vehicle.id: expected an id of 1-32"),
    ({**MINIMAL, "log": {"telemetry_hz": "fast"}}, "log.telemetry_hz: expected a finite number, got 'fast'"),
    ({**MINIMAL, "log": {"telemetry_hz": float("inf")}}, "log.telemetry_hz: expected a finite number, got inf"),
    ({**MINIMAL, "log": {"telemetryhz": 5}}, "unknown key log.telemetryhz"),
    ({**MINIMAL, "logs": {}}, "unknown section [logs]"),
    ({**MINIMAL, "autopilot": {"uri": "serial:/dev/ttyTHS2"}}, "expected udpin:HOST:PORT"),
    ({**MINIMAL, "peers": {"allow_unsigned": True, "send_to": ["10.0.0.255"]}}, "peers.send_to: expected HOST:PORT"),
    ({"vehicle": MINIMAL["vehicle"]}, "peers.key_file is not set: give the fleet key file"),
    ({**MINIMAL, "peers": {"key_file": "/nonexistent/fleet.key"}}, "peers.key_file: cannot read"),
    ({**MINIMAL, "state_feed": {"listen": "0.0.0.0:47200"}}, "state_feed.listen 0.0.0.0:47200 is beyond loopback"),
    ({**MINIMAL, "throughput": {"probe": True, "duration_s": 20.0, "period_s": 10.0}}, "exceeds throughput.period_s"),
    ({**MINIMAL, "throughput": {"targets": ["10.0.0.2:5201"]}}, "expected ID=HOST:PORT"),
    ({**MINIMAL, "peers": {"allow_unsigned": True, "rate_hz": 0}}, "peers.rate_hz must be > 0"),
    ({**MINIMAL, "log": {"tlog": "yes"}}, "log.tlog: expected true or false"),
])
def test_bad_config_names_the_file_and_key(data, message):
    with pytest.raises(ConfigError) as err:
        parse_agent_config(data, "agent.toml")
    assert str(err.value).startswith("agent.toml: ") and message in str(err.value)


def test_config_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[vehicle\nid = 1\n")
    with pytest.raises(ConfigError, match="bad.toml: not valid TOML"):
        load_agent_config(bad)
    with pytest.raises(ConfigError, match="cannot read agent config .*missing.toml"):
        load_agent_config(tmp_path / "missing.toml")


def test_deploy_examples_are_valid_configs(tmp_path):
    deploy = Path(__file__).resolve().parents[2] / "deploy"
    for example in deploy.glob("*.toml"):  # as install.sh lays them out: the fleet key beside the config
        shutil.copy(example, tmp_path / example.name)
    (tmp_path / "fleet.key").write_text("ab" * 32 + "\n")
    configs = [load_agent_config(p) for p in tmp_path.glob("*.toml")]
    assert {c.vehicle.role for c in configs} == {"master", "worker"}
    assert all(c.fleet_key is not None and c.fleet_key.secret == bytes.fromhex("ab" * 32) for c in configs)


def test_peer_message_round_trip_and_bad_datagrams():
    state = PeerState("uav2", "worker", 1.7e9, sysid=2, lat_deg=47.1, lon_deg=8.5, alt_m=500.0,
                      vel_ned_mps=(1.0, 0.5, 0.0), battery_pct=80, probe_port=5201, boot="00ff00ff00ff00ff", seq=7)
    back = decode_peer_state(encode_peer_state(state), "10.0.0.2", None)
    assert back == PeerState(**{**state.__dict__, "host": "10.0.0.2"})
    for garbage in (b"\xff\x00", b"[1, 2]", b'{"nac": "other/1"}', b'{"nac": "peer-state/2", "id": "x"}',
                    b'{"nac": "peer-state/2", "id": "x", "role": "worker", "t_s": "soon"}'):
        with pytest.raises(PeerMessageError):
            decode_peer_state(garbage, "10.0.0.9", None)


def test_peer_table_seen_lost_and_back():
    table = PeerTable("uav1", timeout_s=1.0)
    me = PeerState("uav1", "master", 0.0)
    other = PeerState("uav2", "worker", 0.0)
    assert table.update(me, 0.0, 0.0) is False, "our own looped-back broadcast is not a peer"
    assert table.update(other, 0.0, 0.0) is True
    assert table.update(other, 0.5, 0.5) is False
    assert table.expire(1.4) == []
    lost = table.expire(1.6)
    assert [(p.id, round(s, 1)) for p, s in lost] == [("uav2", 1.1)]
    assert table.expire(3.0) == [], "lost is reported once"
    assert table.snapshot(3.0)["uav2"].lost and table.live() == []
    assert table.update(other, 3.1, 3.1) is True, "a peer that comes back is seen again"


def test_jsonl_records_have_time_and_kind_and_no_nan(tmp_path):
    with JsonlLog(tmp_path / "a.jsonl") as log:
        log.write(kinds.LINK_LOST, t_s=5.0, sysid=1, why="silent", silent_s=float("nan"))
        log.write(kinds.MISSION_CURRENT, value=(1.0, float("inf")), previous=None)
    lines = (tmp_path / "a.jsonl").read_text().splitlines()
    assert json.loads(lines[0])["kind"] == "schema"
    assert json.loads(lines[1]) == {"t_s": 5.0, "kind": "link_lost", "sysid": 1, "why": "silent", "silent_s": None}
    assert json.loads(lines[2])["value"] == [1.0, None] and isinstance(json.loads(lines[2])["t_s"], float)


def test_a_log_reopened_after_its_writer_died_mid_record_starts_the_next_record_on_a_line_of_its_own(tmp_path):
    """A master killed mid-write and resumed (--resume), or an agent restarted, appends to its old log: the cut
    record stays one damaged line, and every record written after it reads whole."""
    path = tmp_path / "a.jsonl"
    with JsonlLog(path) as log:
        log.write(kinds.MISSION_ITEM_REACHED, t_s=1.0, seq=1)
    path.write_bytes(path.read_bytes() + b'{"t_s": 2.0, "kind": "mission_it')
    with JsonlLog(path) as log:
        log.write(kinds.MISSION_ITEM_REACHED, t_s=3.0, seq=3)
    read = read_jsonl(path)
    assert [r["seq"] for r in read.records] == [1, 3] and len(read.problems) == 1 and "line 3" in read.problems[0]


def test_a_cut_at_any_byte_of_the_last_record_loses_only_that_record(tmp_path):
    path = tmp_path / "a.jsonl"
    with JsonlLog(path) as log:
        for k in range(3):
            log.write(kinds.MISSION_ITEM_REACHED, t_s=float(k), seq=k)
    whole = path.read_bytes()
    last_start = whole.rstrip(b"\n").rfind(b"\n") + 1
    for cut in range(last_start + 1, len(whole)):
        path.write_bytes(whole[:cut])
        read = read_jsonl(path)
        assert [r["seq"] for r in read.records] == [0, 1]
        assert read.truncated_tail and len(read.problems) == 1
        assert "line 4: last record is incomplete" in read.problems[0] and str(path) in read.problems[0]


def test_corrupt_lines_in_the_middle_are_named_and_skipped(tmp_path):
    path = tmp_path / "a.jsonl"
    path.write_bytes(b'{"t_s": 1, "kind": "a"}\n\x00\x00garbage\n{"no": "kind"}\n{"t_s": 2, "kind": "b"}\n')
    read = read_jsonl(path)
    assert [r["kind"] for r in read.records] == ["a", "b"] and not read.truncated_tail
    assert [p.split(": ")[1] for p in read.problems] == ["line 2", "line 3"]


def test_tlog_layout_is_big_endian_microseconds_then_the_frame(tmp_path):
    with TlogWriter(tmp_path / "x.tlog") as tlog:
        tlog.write(b"\xfd\x01\x02", t_s=1.5)
    data = (tmp_path / "x.tlog").read_bytes()
    assert struct.unpack(">Q", data[:8])[0] == 1_500_000 and data[8:] == b"\xfd\x01\x02"


def test_distance_agrees_with_the_simulators_geodesy():
    home = Home(47.397742, 8.545594, 488.0)
    for east, north, up in [(9.43, 0, 0), (0, 12.8, 3), (-17, 5, 10), (3000, -4000, 0)]:
        lat, lon, alt = enu_to_lla([east, north, up], home)
        d = distance_m({"lat_deg": home.lat_deg, "lon_deg": home.lon_deg, "alt_m": 488.0},
                       {"lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt)})
        assert math.isclose(d, math.dist((0, 0, 0), (east, north, up)), rel_tol=1e-6, abs_tol=1e-3)
    assert distance_m({"lat_deg": None, "lon_deg": 8.0, "alt_m": 0}, {"lat_deg": 1, "lon_deg": 1, "alt_m": 0}) is None


def test_state_feed_distance_between_self_and_peers():
    state = {"self": {"id": "m", "lat_deg": 47.0, "lon_deg": 8.0, "alt_m": 500.0},
             "peers": {"w1": {"lat_deg": 47.0, "lon_deg": 8.0, "alt_m": 510.0}}}
    assert math.isclose(distance_between(state, "m", "w1"), 10.0, rel_tol=1e-9)
    assert distance_between(state, "m", "w9") is None


def _snapshot() -> AgentSnapshot:
    table = PeerTable("m", timeout_s=3.0)
    table.update(PeerState("w1", "worker", 1000.0, 2, 47.0, 8.0, 510.0, (1.0, 0.5, -0.25), 80, 5201, "MPICH 5",
                           "10.0.0.2"), 10.0, 1000.0)
    table.update(PeerState("w2", "worker", 1000.5, 3, probe_port=5201), 10.5, 1000.5)
    table.expire(13.2)  # w1 silent 3.2 s: lost; w2 2.7 s
    own = OwnState.of(PeerState("m", "master", 1001.0, 1, 47.0, 8.0, 500.0, (0.0, 0.0, 0.0), 95, 5201, "MPICH 5"),
                      link_up=True)
    return AgentSnapshot(1001.25, own, tuple(table.snapshot(14.0).values()))


def test_the_agents_snapshot_is_typed_and_finds_everyone():
    snapshot = _snapshot()
    assert [(p.state.id, p.age_s, p.lost) for p in snapshot.peers] == [("w1", 4.0, True), ("w2", 3.5, False)]
    assert snapshot.vehicle("m") is snapshot.own and snapshot.vehicle("w1").alt_m == 510.0
    assert snapshot.vehicle("w9") is None
    assert math.isclose(snapshot.distance_m("m", "w1"), 10.0, rel_tol=1e-9)
    assert snapshot.distance_m("m", "w2") is None and snapshot.distance_m("m", "w9") is None  # w2: no position yet


def test_the_state_feed_writes_the_snapshot_in_its_wire_format_byte_for_byte():
    """The MPI job and `nac-onboard state` read this JSON (nac_onboard/compute/positions.py): its keys, their order
    and values are the wire format."""
    snapshot = _snapshot()
    data = encode_snapshot(snapshot)
    assert data == (
        b'{"t_s":1001.25,"self":{"id":"m","role":"master","sysid":1,"lat_deg":47.0,"lon_deg":8.0,"alt_m":500.0,'
        b'"vel_ned_mps":[0.0,0.0,0.0],"battery_pct":95,"mpi_build":"MPICH 5","link_up":true},"peers":{'
        b'"w1":{"id":"w1","role":"worker","t_s":1000.0,"sysid":2,"lat_deg":47.0,"lon_deg":8.0,"alt_m":510.0,'
        b'"vel_ned_mps":[1.0,0.5,-0.25],"battery_pct":80,"probe_port":5201,"mpi_build":"MPICH 5","host":"10.0.0.2",'
        b'"boot":"","age_s":4.0,"lost":true},'
        b'"w2":{"id":"w2","role":"worker","t_s":1000.5,"sysid":3,"lat_deg":null,"lon_deg":null,"alt_m":null,'
        b'"vel_ned_mps":null,"battery_pct":null,"probe_port":5201,"mpi_build":"","host":"","boot":"","age_s":3.5,'
        b'"lost":false}}}')
    answer = json.loads(data)
    assert distance_between(answer, "m", "w1") == snapshot.distance_m("m", "w1")
    unknown = OwnState.of(PeerState("m", "master", 1001.0), link_up=False)
    assert encode_snapshot(AgentSnapshot(5.0, unknown)) == (
        b'{"t_s":5.0,"self":{"id":"m","role":"master","sysid":0,"lat_deg":null,"lon_deg":null,"alt_m":null,'
        b'"vel_ned_mps":null,"battery_pct":null,"mpi_build":"","link_up":false},"peers":{}}')


def test_the_state_feed_hands_the_masters_probes_to_the_mpi_job(monkeypatch):
    """A vehicle that probes adds each peer's latest rate to its answer; the MPI master (FeedDistances) takes a
    rate no older than its bound and nothing that is not a finite, non-negative rate."""
    snapshot = dataclasses.replace(_snapshot(), probes=(ProbeResult("w1", 12.5e6, 1.0), ProbeResult("w2", 0.0, 0.5)))
    answer = json.loads(encode_snapshot(snapshot))
    assert answer["probes"] == {"w1": {"bits_per_second": 12.5e6, "age_s": 1.0},
                                "w2": {"bits_per_second": 0.0, "age_s": 0.5}}
    assert "probes" not in json.loads(encode_snapshot(_snapshot())), "a vehicle that does not probe: no key"
    feed = FeedDistances("127.0.0.1:1", ["m", "w1", "w2", "w3"])
    monkeypatch.setattr(positions, "fetch_state", lambda address, timeout_s: answer)
    # w1 is lost to the agent: its last position is not believed, and the job does not send it work
    assert feed.distances_m(0, 0.0) == {1: None, 2: None, 3: None} and feed.lost_ranks() == {1}
    assert feed.measured_rates_bps(max_age_s=5.0) == {1: 12.5e6, 2: 0.0, 3: None}
    assert feed.measured_rates_bps(max_age_s=0.75) == {1: None, 2: 0.0, 3: None}, "too old: not believed"
    for bad in ({"w1": {"bits_per_second": "fast", "age_s": 1}}, {"w1": {"bits_per_second": -1, "age_s": 1}},
                {"w1": {"bits_per_second": 1e6, "age_s": True}}, {"w1": [1e6]}, ["w1"]):
        feed.state = {**answer, "probes": bad}
        assert feed.measured_rates_bps(max_age_s=5.0)[1] is None, bad
    heard = {"self": {"id": "m"}, "peers": {"w2": {"id": "w2", "boot": "00000000000000aa", "lost": False}}}
    monkeypatch.setattr(positions, "fetch_state", lambda address, timeout_s: heard)
    feed.distances_m(1, 0.0)
    assert feed.lost_ranks() == set()
    heard["peers"]["w2"]["boot"] = "00000000000000bb"  # its companion rebooted: the rank of the old boot is gone
    assert feed.lost_ranks() == {2}
    del heard["peers"]["w2"]  # forgotten by the agent, silent longer than its forget_s: lost all the same
    assert feed.lost_ranks() == {2}


def test_systemd_notifier_speaks_the_notify_protocol(tmp_path):
    path = str(tmp_path / "notify")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as server:
        server.bind(path)
        notifier = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
        assert notifier.watchdog_period_s == 1.0
        assert notifier.ready("up")
        assert server.recv(100) == b"READY=1\nSTATUS=up"
        notifier.watchdog()
        assert server.recv(100) == b"WATCHDOG=1"
        notifier.close()
    outside = SystemdNotifier({})
    assert not outside.ready() and outside.watchdog_period_s is None
    other_pid = SystemdNotifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000", "WATCHDOG_PID": "1"})
    assert other_pid.watchdog_period_s is None, "the watchdog is meant for another process"


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), st.integers(0, 7), st.floats(0.0, 0.3)), min_size=1, max_size=400))
def test_statustext_floods_are_logged_rate_limited_and_every_text_counted(texts):
    """Any sequence of STATUSTEXTs: at most per_s records in any second, the same text at most once per repeat_s,
    and every text either logged or counted on a later record (nothing vanishes without a count)."""
    limiter = TextLimiter(per_s=5, repeat_s=2.0)
    now, records = 0.0, []
    for text, severity, step_s in texts:
        now += step_s
        record = limiter.offer(severity, f"text {text}", now)
        if record is not None:
            records.append((now, record))
    final = limiter.flush()
    counted = sum(1 + r.get("repeated", 0) + r.get("dropped_since_last", 0) for _, r in records)
    counted += (final.get("repeated", 0) + final.get("dropped_since_last", 0)) if final else 0
    assert counted == len(texts)
    assert final is None or final["counts_only"] is True, "the stop's record says it is no text heard again"
    times = [t for t, _ in records]
    assert all(times[k + 5] - times[k] >= 1.0 for k in range(len(times) - 5)), "at most 5 records a second"
    for (t0, r0), (t1, r1) in zip(records, records[1:], strict=False):
        if (r0["severity"], r0["text"]) == (r1["severity"], r1["text"]):
            assert t1 - t0 >= 2.0, "the same text again at once is counted, not logged"
