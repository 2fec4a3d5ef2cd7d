"""The agent's autopilot link has one peer (issue 34): from any other address no frame is taken (a spoofed armed
HEARTBEAT or a GLOBAL_POSITION_INT 10 degrees away changes neither the telemetry records nor the state feed) and
nothing the agent sends reaches it (a ground tool's routed ARM goes to the autopilot only), on UDP and TCP.
The intruders are generated: many source ports on two loopback addresses, random payloads around the spoofed frames."""

from __future__ import annotations

import json
import random
import select
import socket
import threading

import pytest

from missions.model import MavCmd
from nac_onboard.agent.state_feed import fetch_state
from tests.conftest import free_port
from tests.integration.agents import agent_toml, kind, wait_for_record
from tests.integration.test_agent import run_dir

ARMED = 128  # MAV_MODE_FLAG_SAFETY_ARMED
SPOOF_OFFSET_DEG = 10.0


def spoofed_frames(sysid: int, lat_deg: float, lon_deg: float, rng: random.Random) -> list[bytes]:
    """What an intruder sends as the autopilot: an armed HEARTBEAT, a position 10 degrees away, and garbage."""
    from pymavlink.dialects.v20 import ardupilotmega as dialect

    mav = dialect.MAVLink(None, srcSystem=sysid, srcComponent=1)
    heartbeat = mav.heartbeat_encode(dialect.MAV_TYPE_QUADROTOR, dialect.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                     ARMED | dialect.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 3, 4).pack(mav)
    position = mav.global_position_int_encode(10**9, int((lat_deg + SPOOF_OFFSET_DEG) * 1e7),
                                              int((lon_deg + SPOOF_OFFSET_DEG) * 1e7), 900_000, 400_000,
                                              0, 0, 0, 0).pack(mav)
    junk = rng.randbytes(rng.randint(1, 300))
    return [heartbeat, position, heartbeat + position, junk, b"\xfd" + junk]


def intruder_sockets(count: int, rng: random.Random) -> list[socket.socket]:
    """count UDP sockets on random source ports of 127.0.0.1 and 127.0.0.2 (another host, as far as the agent
    can tell)."""
    out = []
    for _ in range(count):
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.bind((rng.choice(["127.0.0.1", "127.0.0.2"]), 0))
        sock.setblocking(False)
        out.append(sock)
    return out


def heard_anything(socks: list[socket.socket]) -> list[tuple[str, int]]:
    """The intruders that received a datagram or a byte (they are all non-blocking)."""
    heard = []
    for sock in socks:
        try:
            data = sock.recv(65535)
        except (BlockingIOError, ConnectionRefusedError):
            continue
        if data:
            heard.append(sock.getsockname())
    return heard


def companion_source(sim) -> tuple[str, int]:
    """Where the SITL's companion link sends from (its socket is bound to an ephemeral port)."""
    connection = next(c for c in sim.protocols[0].connections if c.kind == "companion" and not c.tcp)
    return connection.sock.getsockname()


def assert_truth_kept(log_path, feed, sim, after_s: float) -> None:
    """Telemetry written after after_s (agent clock in t_s) and the state feed hold the SITL's truth."""
    from nac_onboard.flight_log import read_jsonl

    truth = sim.truth(0)
    records = [r for r in read_jsonl(log_path).records if r["kind"] == "telemetry" and r["t_s"] >= after_s]
    assert records, "telemetry was still logged during the spoofing"
    for record in records:
        assert not record["armed"], record
        assert abs(record["lat_deg"] - truth["lat_deg"]) < 0.01 and abs(record["lon_deg"] - truth["lon_deg"]) < 0.01
    own = fetch_state(feed)["self"]
    assert abs(own["lat_deg"] - truth["lat_deg"]) < 0.01 and abs(own["lon_deg"] - truth["lon_deg"]) < 0.01, own
    assert not sim.truth(0)["armed"]


@pytest.mark.parametrize("configured", [False, True], ids=["first-sender", "configured-peer"])
def test_udp_autopilot_link_takes_and_answers_only_its_peer(start_sitl, start_agent, tmp_path, configured):
    import time

    from pymavlink import mavutil

    rng = random.Random(34_000 + configured)
    sim = start_sitl(speedup=5.0)
    port = sim.config.companion_base_port
    host, sitl_port = companion_source(sim)
    tool_port, feed_port = free_port(), free_port()
    intruders = intruder_sockets(40, rng)
    tool = mavutil.mavlink_connection(f"udpin:127.0.0.1:{tool_port}", source_system=250)
    try:
        autopilot = {"peer": f"{host}:{sitl_port}"} if configured else {}
        start_agent(agent_toml("uav1", "master", 1, f"udpin:127.0.0.1:{port}", tmp_path / "runs", free_port(), [],
                               autopilot=autopilot, routing={"endpoints": [f"udpout:127.0.0.1:{tool_port}"]},
                               state_feed={"listen": f"127.0.0.1:{feed_port}"}))
        log_path = run_dir(tmp_path) / "agent.jsonl"
        wait_for_record(log_path, kind("link_up"))
        wait_for_record(log_path, lambda r: r["kind"] == "telemetry")
        truth = sim.truth(0)
        spoof_start_s = time.time()
        for _round in range(5):
            for sock in intruders:
                for frame in spoofed_frames(1, truth["lat_deg"], truth["lon_deg"], rng):
                    sock.sendto(frame, ("127.0.0.1", port))
        # telemetry records after the spoofing (the agent logs at 10 Hz): all from the SITL
        wait_for_record(log_path, lambda r: r["kind"] == "telemetry" and r["t_s"] > spoof_start_s + 0.3)
        assert_truth_kept(log_path, f"127.0.0.1:{feed_port}", sim, spoof_start_s)
        # the ground tool's ARM goes through the agent to the SITL only
        assert tool.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0) is not None
        while tool.recv_match(blocking=False) is not None:
            pass  # the telemetry routed to the tool meanwhile: a full socket buffer would drop the answer
        ack = None
        for _try in range(3):  # as ground stations do: a lost datagram is sent again
            tool.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            if (ack := tool.recv_match(type="COMMAND_ACK", blocking=True, timeout=2.0)) is not None:
                break
        assert ack is not None and sim.truth(0)["armed"], "the routed ARM reached the autopilot"
        assert heard_anything(intruders) == [], "nothing the agent sends reaches an intruder"
        taken = wait_for_record(log_path, kind("autopilot_peer"))
        assert taken["peer"] == f"{host}:{sitl_port}", "the SITL is the autopilot"
        refused = wait_for_record(log_path, kind("autopilot_refused"))
        assert refused["last_sender"].rsplit(":", 1)[0] in ("127.0.0.1", "127.0.0.2")
        assert refused["last_sender"] != taken["peer"] and refused["peer"] == taken["peer"]
    finally:
        tool.close()
        for sock in intruders:
            sock.close()


class Relay:
    """A TCP bridge from the SITL's TCP server to the agent's tcpin: link, connecting from a chosen address (the
    autopilot on a Pixhawk's Ethernet would connect itself; the SITL only accepts)."""

    def __init__(self, sitl_port: int, agent_port: int, source: str):
        self.sitl = socket.create_connection(("127.0.0.1", sitl_port), timeout=5.0)
        self.agent = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.agent.bind((source, 0))
        self.agent.settimeout(5.0)
        self.agent.connect(("127.0.0.1", agent_port))
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        pair = {self.sitl: self.agent, self.agent: self.sitl}
        while not self.stop.is_set():
            ready, _, _ = select.select(list(pair), [], [], 0.1)
            for sock in ready:
                try:
                    data = sock.recv(65536)
                except OSError:
                    return
                if not data:
                    return
                pair[sock].sendall(data)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5.0)
        self.sitl.close()
        self.agent.close()


def test_tcp_autopilot_link_keeps_one_connection_from_its_peer(start_sitl, start_agent, tmp_path, base_port):
    """tcpin: with autopilot.peer = "127.0.0.1": connections from 127.0.0.2 (before and after the autopilot's)
    and a second one from the peer's host are closed at once; the spoofed frames they send are not believed."""
    import time

    rng = random.Random(3434)
    sim = start_sitl(speedup=5.0, tcp_base_port=base_port(1) + 5)
    agent_port, feed_port = free_port(), free_port()
    start_agent(agent_toml("uav1", "master", 1, f"tcpin:127.0.0.1:{agent_port}", tmp_path / "runs", free_port(), [],
                           autopilot={"peer": "127.0.0.1"}, state_feed={"listen": f"127.0.0.1:{feed_port}"}))
    log_path = run_dir(tmp_path) / "agent.jsonl"
    wait_for_record(log_path, kind("agent_ready"))

    def intrude(source: str) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.bind((source, 0))
        sock.settimeout(5.0)
        sock.connect(("127.0.0.1", agent_port))
        try:
            for frame in spoofed_frames(1, 0.0, 0.0, rng):
                sock.sendall(frame)
        except OSError:
            pass  # already closed by the agent
        return sock

    early = [intrude("127.0.0.2") for _ in range(5)]
    relay = Relay(sim.config.tcp_base_port, agent_port, "127.0.0.1")
    try:
        wait_for_record(log_path, kind("link_up"))
        wait_for_record(log_path, lambda r: r["kind"] == "telemetry")
        spoof_start_s = time.time()
        late = [intrude(rng.choice(["127.0.0.1", "127.0.0.2"])) for _ in range(10)]
        for sock in early + late:  # each is closed by the agent without a byte: EOF (or a reset)
            try:
                assert sock.recv(65535) == b"", "the agent sent something to an intruder"
            except ConnectionResetError:
                pass
            sock.close()
        refused = wait_for_record(log_path, lambda r: r["kind"] == "autopilot_refused", timeout_s=15.0)
        assert refused["refused_since_last_record"] >= 1
        wait_for_record(log_path, lambda r: r["kind"] == "telemetry" and r["t_s"] > spoof_start_s + 0.3)
        assert_truth_kept(log_path, f"127.0.0.1:{feed_port}", sim, spoof_start_s)
    finally:
        relay.close()


def test_agent_stopped_counts_refusals(start_sitl, start_agent, tmp_path):
    """The count reaches agent_stopped: an operator sees how much was refused over the whole run."""
    rng = random.Random(7)
    sim = start_sitl(speedup=5.0)
    port = sim.config.companion_base_port
    agent = start_agent(agent_toml("uav1", "worker", 1, f"udpin:127.0.0.1:{port}", tmp_path / "runs", free_port(),
                                   []))
    log_path = run_dir(tmp_path) / "agent.jsonl"
    wait_for_record(log_path, kind("link_up"))
    intruders = intruder_sockets(20, rng)
    try:
        for sock in intruders:
            sock.sendto(b"\x00", ("127.0.0.1", port))
        wait_for_record(log_path, kind("autopilot_refused"))
    finally:
        for sock in intruders:
            sock.close()
    assert agent.stop() == 0
    stopped = json.loads(log_path.read_text().splitlines()[-1])
    assert stopped["kind"] == "agent_stopped" and 1 <= stopped["autopilot_refused"] <= 20, stopped
