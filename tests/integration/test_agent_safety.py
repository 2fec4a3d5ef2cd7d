"""A running agent under hostile peer traffic: it stays up, believes only signed state from its fleet, logs the
refusals (rate-limited, naming the sender), and its state feed answers only a well-formed request."""

import json
import secrets
import socket
import subprocess
import sys
import time

from nac_onboard.agent.peers import FleetKey, PeerState, encode_peer_state, sign
from nac_onboard.agent.state_feed import REQUEST, fetch_state
from nac_onboard.flight_log import read_jsonl
from nac_onboard.mavlink.signing import load_signing_key
from tests.conftest import free_port
from tests.integration.agents import agent_toml, fleet_key, kind, wait_for_record
from tests.integration.test_agent import companion_uri, run_dir

W9 = b'{"nac":"peer-state/2","id":"w9","role":"worker","boot":"0123456789abcdef","seq":1,"t_s":1,'
KILLERS = [W9 + b'"battery_pct":1e400}', W9 + b'"lat_deg":' + b"9" * 400 + b"}",
           b"[" * 1500]  # each once stopped the agent; signed here, as a fleet member with a bug would send them


FLOOD = 300  # forged datagrams from one sender


def test_hostile_peer_datagrams_do_not_stop_the_agent_and_forged_state_is_not_believed(start_sitl, start_agent,
                                                                                      tmp_path):
    sim = start_sitl(speedup=5.0)
    peer_port, feed_port = free_port(), free_port()
    config = agent_toml("uav1", "master", 1, companion_uri(sim, 0), tmp_path / "runs", peer_port, [],
                        state_feed={"listen": f"127.0.0.1:{feed_port}"})
    agent = start_agent(config)
    log_path = run_dir(tmp_path) / "agent.jsonl"
    wait_for_record(log_path, kind("agent_ready"))
    key = FleetKey("fleet", load_signing_key(fleet_key(tmp_path / "runs")))
    now = time.time()
    forged = encode_peer_state(PeerState("intruder", "worker", now, lat_deg=47.0, lon_deg=8.0, alt_m=500.0))
    wrong_key = encode_peer_state(PeerState("intruder2", "worker", now), FleetKey("fleet", b"y" * 32))
    w1_boot, w1_start = secrets.token_hex(8), time.monotonic()

    def w1_state(**position) -> PeerState:  # as w1's agent stamps it: its boot, its monotonic milliseconds
        return PeerState("w1", "worker", time.time(), boot=w1_boot, seq=int((time.monotonic() - w1_start) * 1000) + 1,
                         **position)

    genuine = encode_peer_state(w1_state(lat_deg=47.0, lon_deg=8.0, alt_m=500.0), key)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        hostile = [*(sign(k, key) for k in KILLERS), b"\x00" * 3000, forged, wrong_key]
        for datagram in [*hostile, genuine, genuine]:  # the second genuine one is a replay
            sock.sendto(datagram, ("127.0.0.1", peer_port))
        wait_for_record(log_path, kind("peer_seen", peer="w1"))
        # the feed answers only the request it knows: a 1-byte datagram gets nothing back
        sock.sendto(b"x", ("127.0.0.1", feed_port))
        sock.settimeout(0.5)
        try:
            reflected = sock.recvfrom(65535)
        except TimeoutError:
            reflected = None
        assert reflected is None
    state = fetch_state(f"127.0.0.1:{feed_port}")
    assert set(state["peers"]) == {"w1"}, "only the fleet's signed state is believed"
    # a flood of forgeries from one sender mutes that sender; the fleet's peer, from its own port, is still heard
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as flood, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as w1:
        for _ in range(FLOOD):
            flood.sendto(wrong_key, ("127.0.0.1", peer_port))
        deadline = time.monotonic() + 5.0
        while fetch_state(f"127.0.0.1:{feed_port}")["peers"]["w1"]["lat_deg"] != 47.001:
            # sent again until taken, as a peer does at its rate: the flood may have filled the socket's buffer
            moved = w1_state(lat_deg=47.001, lon_deg=8.0, alt_m=500.0)
            w1.sendto(encode_peer_state(moved, key), ("127.0.0.1", peer_port))
            assert time.monotonic() < deadline, "the genuine peer's new state was not taken during the flood"
            time.sleep(0.05)
    assert agent.alive(), agent.stderr_text()
    rejected = wait_for_record(log_path, kind("peer_rejected"))
    assert rejected["last_sender"] == "127.0.0.1"
    assert agent.stop() == 0
    stopped = json.loads(log_path.read_text().splitlines()[-1])
    assert stopped["kind"] == "agent_stopped"
    rejects = stopped["peer_rejects"]
    # 50 refusals a second, then muted (the socket's buffer may have dropped some of the flood before)
    assert rejects["bad_signature"] == 1 + 51 and 0 < rejects["muted"] <= FLOOD - 51, rejects
    assert {k: n for k, n in rejects.items() if k not in ("bad_signature", "muted")} == {
        "schema": 2, "not_json": 1, "too_big": 1, "unsigned": 1, "replayed": 1}, rejects
    assert stopped["bad_feed_requests"] == 1 and stopped["feed_requests"] >= 1
    assert REQUEST == b'{"get":"state"}'


def test_routing_takes_commands_only_from_its_configured_tool(start_sitl, start_agent, tmp_path):
    """An ARM from an unknown local address to a routing endpoint once armed the vehicle; now only the tool the
    config names is heard, a watch endpoint gets telemetry and cannot command, and refusals are logged."""
    from pymavlink import mavutil

    from missions.model import MavCmd

    sim = start_sitl(speedup=5.0)
    tool_port, watcher_port = free_port(), free_port()
    tool = mavutil.mavlink_connection(f"udpin:127.0.0.1:{tool_port}", source_system=250)
    watcher = mavutil.mavlink_connection(f"udpin:127.0.0.1:{watcher_port}", source_system=251)
    try:
        start_agent(agent_toml("uav1", "master", 1, companion_uri(sim, 0), tmp_path / "runs", free_port(), [],
                               routing={"endpoints": [f"udpout:127.0.0.1:{tool_port}"],
                                        "watch": [f"udpout:127.0.0.1:{watcher_port}"]}))
        for conn in (tool, watcher):
            assert conn.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0) is not None
        agent_host, agent_port = next(iter(tool.clients))  # the agent's socket for the tool, as the tool saw it
        attacker = mavutil.mavlink_connection(f"udpout:{agent_host}:{agent_port}", source_system=66)
        try:
            for _ in range(5):  # an intruder aims at the tool endpoint's socket; the watcher tries too
                attacker.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
                watcher.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            refused = wait_for_record(run_dir(tmp_path) / "agent.jsonl", kind("routing_refused"))
            assert refused["frames_since_last_record"] >= 1
            # a barrier: the tool's own request travels the same path after the intruders' frames
            tool.mav.command_long_send(1, 1, MavCmd.REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0)
            assert tool.recv_match(type="COMMAND_ACK", blocking=True, timeout=3.0) is not None
            assert not sim.truth(0)["armed"], "nobody but the configured tool may arm the vehicle"
            tool.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            ack = tool.recv_match(type="COMMAND_ACK", blocking=True, timeout=3.0)
            assert ack is not None and sim.truth(0)["armed"], "the configured tool still commands it"
        finally:
            attacker.close()
    finally:
        tool.close()
        watcher.close()


def test_a_udpin_routing_endpoint_answers_only_the_first_peer_or_the_allowed_ones():
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    from nac_onboard.mavlink.routing import RawEndpoint

    frame = dialect.MAVLink(None, srcSystem=250).heartbeat_encode(6, 8, 0, 0, 0).pack(dialect.MAVLink(None))
    port = free_port()
    endpoint = RawEndpoint(f"udpin:127.0.0.1:{port}")
    senders = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(3)]
    try:
        for s in senders:
            s.bind(("127.0.0.1", 0))
        allowed = RawEndpoint(f"udpin:127.0.0.1:{free_port()}", allow=(senders[2].getsockname(),))
        try:
            for s in senders:
                s.sendto(frame, ("127.0.0.1", port))
                s.sendto(frame, allowed.sock.getsockname())
            # loopback delivers a datagram into the receiver's queue before sendto returns: all are there now
            assert len(endpoint.read_frames()) == 1 and endpoint.dropped_frames == 2
            assert endpoint.peer == senders[0].getsockname()
            assert endpoint.write(frame) and senders[0].recv(512) == frame
            assert len(allowed.read_frames()) == 1 and allowed.dropped_frames == 2, "only the allowed sender"
        finally:
            allowed.close()
    finally:
        endpoint.close()
        for s in senders:
            s.close()



def test_a_dead_throughput_server_is_restarted_with_an_event(tmp_path):
    """Inside the agent the server thread once died silently, and every later probe read as a lost link."""
    from nac_onboard.agent.config import parse_agent_config
    from nac_onboard.agent.daemon import Agent
    from nac_onboard.link.throughput import probe
    from nac_onboard.tomlfile import read_toml

    path = tmp_path / "agent.toml"
    path.write_text(agent_toml("uav2", "worker", 2, f"udpin:127.0.0.1:{free_port()}", tmp_path / "runs",
                               free_port(), []))
    agent = Agent(parse_agent_config(read_toml(path, "agent config"), str(path)), tmp_path / "runs" / "test" / "uav2")
    try:
        agent.open()
        port = agent.throughput_server.port
        agent.throughput_server.stop()  # as if its thread had died
        assert not agent.throughput_server.alive
        agent._supervise_throughput_server()
        assert agent.throughput_server.alive and agent.throughput_server.port == port
        assert probe("127.0.0.1", port, duration_s=0.2, interval_s=0.1)["end"]["sum_received"]["bytes"] > 0
    finally:
        agent.close()
    assert wait_for_record(tmp_path / "runs" / "test" / "uav2" / "agent.jsonl", kind("throughput_server_restarted"))


# ---- issue 34, peer state ------------------------------------------------------------------------------------------
def test_a_peer_datagram_replayed_after_the_agent_restarts_is_refused(start_agent, tmp_path):
    """The agent keeps the last sequence it accepted from each peer across its restart: a datagram heard before
    the restart, sent again after it (still inside replay_window_s by the clock), is refused as replayed; the
    peer's next message is taken."""
    peer_port, feed_port = free_port(), free_port()
    config = agent_toml("m", "master", 1, f"udpin:127.0.0.1:{free_port()}", tmp_path / "runs", peer_port, [],
                        state_feed={"listen": f"127.0.0.1:{feed_port}"})
    log_path = tmp_path / "runs" / "test" / "m" / "agent.jsonl"
    key = FleetKey("fleet", load_signing_key(fleet_key(tmp_path / "runs")))
    boot, start = secrets.token_hex(8), time.monotonic()

    def w1(k: int) -> bytes:
        state = PeerState("w1", "worker", time.time(), boot=boot, lat_deg=47.0 + k / 1000, lon_deg=8.0, alt_m=500.0,
                          seq=int((time.monotonic() - start) * 1000) + k)
        return encode_peer_state(state, key)

    sent = []
    agent = start_agent(config, name="before")
    wait_for_record(log_path, kind("agent_ready"))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        while not sent or fetch_state(f"127.0.0.1:{feed_port}")["peers"].get("w1", {}).get("lat_deg") != 47.0 + (
                len(sent) - 1) / 1000:
            sent.append(w1(len(sent)))  # until the last one sent is taken
            sock.sendto(sent[-1], ("127.0.0.1", peer_port))
            assert len(sent) < 200, "the agent never took w1's state"
        assert agent.stop() == 0
        freshness = tmp_path / "runs" / "peer-freshness-m.json"
        assert boot in json.loads(freshness.read_text())["peers"]["w1"]
        start_agent(config, name="after")  # returns at its ready line: its sockets are open
        replayed = sent[secrets.randbelow(len(sent))]
        sock.sendto(replayed, ("127.0.0.1", peer_port))
        wait_for_record(log_path, kind("peer_rejected", last_reason="replayed"))
        assert "w1" not in fetch_state(f"127.0.0.1:{feed_port}")["peers"], "the replay was not believed"
        deadline = time.monotonic() + 5.0
        while "w1" not in fetch_state(f"127.0.0.1:{feed_port}")["peers"]:
            sock.sendto(w1(len(sent)), ("127.0.0.1", peer_port))
            assert time.monotonic() < deadline, "w1's next message was not taken after the restart"
            time.sleep(0.05)


def test_a_weak_fleet_passphrase_stops_the_agent_with_exit_2_naming_the_field(tmp_path):
    passphrase = secrets.token_urlsafe(12)[: 1 + secrets.randbelow(15)]  # 1-15 characters
    key_file = tmp_path / "weak.key"
    key_file.write_text(passphrase + "\n")
    config = tmp_path / "weak.toml"
    config.write_text(f'[vehicle]\nid = "w1"\nrole = "worker"\n[peers]\nkey_file = "{key_file}"\n')
    result = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "agent", "--config", str(config)],
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 2, result.stderr
    assert f"{config}: peers.key_file: " in result.stderr and "at least 16 characters" in result.stderr
    assert "Traceback" not in result.stderr


STATUSTEXT_FLOOD_TEXTS = 40  # distinct texts, each sent again and again


def test_a_statustext_flood_from_the_autopilot_grows_the_log_by_a_bounded_amount(start_agent, tmp_path):
    """An autopilot (here a fake one on the agent's UDP link) sending STATUSTEXT as fast as it can: the agent logs
    at most 10 records in any second, the same text at most once per 5 s, and counts the rest on the records."""
    from pymavlink import mavutil

    from nac_onboard.mavlink.dialect import M

    port = free_port()
    config = agent_toml("uav1", "worker", 1, f"udpin:127.0.0.1:{port}", tmp_path / "runs", free_port(), [])
    agent = start_agent(config)
    log_path = tmp_path / "runs" / "test" / "uav1" / "agent.jsonl"
    wait_for_record(log_path, kind("agent_ready"))
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
    sent = 0
    try:
        autopilot.mav.heartbeat_send(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, M.MAV_STATE_STANDBY)
        wait_for_record(log_path, kind("link_up"))
        deadline = time.monotonic() + 20.0
        while not any(r.get("dropped_since_last") for r in read_jsonl(log_path).records
                      if r["kind"] == "statustext") or sent < 5000:
            for _ in range(500):
                text = f"PreArm: flood {secrets.randbelow(STATUSTEXT_FLOOD_TEXTS)}".encode()
                autopilot.mav.statustext_send(M.MAV_SEVERITY_WARNING, text)
                sent += 1
            autopilot.mav.heartbeat_send(M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                         M.MAV_STATE_STANDBY)
            assert time.monotonic() < deadline, "no statustext record counted dropped texts"
            time.sleep(0.01)  # the pace of a fast autopilot link, so the socket's buffer holds most of it
    finally:
        autopilot.close()
    assert agent.stop() == 0
    records = [r for r in read_jsonl(log_path).records if r["kind"] == "statustext"]
    # each record is a text heard, plus what it counts; the stop's last one carries counts only
    counted = sum((0 if r.get("counts_only") else 1) + r.get("repeated", 0) + r.get("dropped_since_last", 0)
                  for r in records)
    assert len(records) < counted <= sent, (len(records), counted, sent)
    times = [r["t_s"] for r in records[:-1]]  # the last: written at the stop with what was counted since
    assert all(times[k + 10] - times[k] >= 0.99 for k in range(len(times) - 10)), ("more than 10 records a second",
                                                                                     times)
    assert all(len(r) <= 6 + bool(r.get("counts_only")) for r in records)
    # a record's size is bounded by its fields (at most 6: a 50-character text, numbers and counts), not by how
    # many texts it counts: a loaded run's 12 records averaged 100.6 bytes, their counts having more digits
    largest = max(len(json.dumps(r)) for r in records)
    assert largest <= 200 and len(records) < sent / 10, (largest, len(records), sent)
