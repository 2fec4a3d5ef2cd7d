"""The onboard agent as it runs on a Jetson: a child process on the SITL's companion port, real sockets."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from pymavlink import mavutil

from missions.builder import waypoint_mission
from missions.geo import lla_to_enu
from missions.model import MavCmd
from nac_onboard.agent.state_feed import fetch_state
from nac_onboard.flight_log import read_jsonl
from nac_onboard.mavlink.dialect import M
from tests.conftest import free_port
from tests.integration.agents import agent_toml, kind, wait_for_record

# 20 m legs: about 3.5 s of wall-clock flight at 10x, so "more than 30 records at 10 Hz" has a margin (12 m legs
# flew exactly 3 s and logged 30 or 31 by the logger's phase, or an arm heard a batch later on a busy machine).
LEGS_M = [(20, 0), (20, 20), (0, 20)]


def companion_uri(sim, vehicle: int = 0) -> str:
    return f"udpin:127.0.0.1:{sim.config.companion_base_port + sim.config.port_step * vehicle}"


def one_agent(sim, tmp_path, vehicle: int = 0, role: str = "master", **sections) -> str:
    return agent_toml(f"uav{vehicle + 1}", role, vehicle + 1, companion_uri(sim, vehicle), tmp_path / "runs",
                      free_port(), [], **sections)


def run_dir(tmp_path, vehicle: int = 0) -> Path:
    return tmp_path / "runs" / "test" / f"uav{vehicle + 1}"


def test_logged_positions_match_truth_and_every_mission_item_is_an_event(start_sitl, gcs_for, start_agent,
                                                                          tmp_path):
    sim = start_sitl(speedup=10.0)
    trace: list[tuple[float, np.ndarray]] = []
    sim.world.step_observers.append(lambda t, s: trace.append((t, s.pos_m[0].copy())))
    agent = start_agent(one_agent(sim, tmp_path))
    log_path = run_dir(tmp_path) / "agent.jsonl"
    wait_for_record(log_path, kind("link_up"))

    gcs = gcs_for(sim, 0)
    home = sim.homes[0]
    items = waypoint_mission(home.lat_deg, home.lon_deg, LEGS_M, alt_m=8.0)
    assert gcs.upload(items) == M.MAV_MISSION_ACCEPTED
    assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert gcs.command(MavCmd.MISSION_START, 0, 0) == M.MAV_RESULT_ACCEPTED
    last = len(items) - 1
    assert gcs.recv("MISSION_ITEM_REACHED", 60.0, lambda m: m.seq == last) is not None
    wait_for_record(log_path, kind("mission_item_reached", seq=last))
    assert agent.stop() == 0, agent.stderr_text()

    read = read_jsonl(log_path)
    assert read.problems == []
    assert read.records[-1]["kind"] == "agent_stopped"
    reached = [r["seq"] for r in read.of_kind("mission_item_reached")]
    assert reached == list(range(1, len(items)))
    assert {"AUTO"} <= {r["value"] for r in read.of_kind("mode")}

    steps = list(trace)  # one snapshot: the simulator thread keeps appending
    times = np.array([t for t, _ in steps])
    truth = np.array([p for _, p in steps])
    telemetry = [r for r in read.of_kind("telemetry") if r["armed"]]
    assert len(telemetry) > 30, "the flight should give several seconds of 10 Hz telemetry"
    errors = []
    for r in telemetry:
        t_s = r["time_boot_ms"] / 1000  # the autopilot's clock for the logged position
        true_enu = [np.interp(t_s, times, truth[:, k]) for k in range(3)]
        logged_enu = lla_to_enu(r["lat_deg"], r["lon_deg"], r["alt_m"], home)
        errors.append(float(np.linalg.norm(logged_enu - true_enu)))
    assert max(errors) < 0.5, f"worst logged position is {max(errors):.2f} m from the truth"
    moving = max(np.hypot(*r["vel_ned_mps"][:2]) for r in telemetry)
    assert moving > 1.0, "the comparison should cover the vehicle in motion"
    wall = np.array([r["t_s"] for r in read.of_kind("telemetry")])
    assert 7.0 < 1 / np.median(np.diff(wall)) < 13.0, "telemetry is logged at log.telemetry_hz (10)"

    # The .tlog opens in pymavlink as any ground station's would, and carries the same positions.
    tlog = mavutil.mavlink_connection(str(run_dir(tmp_path) / "mavlink.tlog"))
    positions = []
    while (msg := tlog.recv_match(type="GLOBAL_POSITION_INT")) is not None:
        positions.append((msg.time_boot_ms, msg.lat / 1e7, msg.lon / 1e7))
    logged = {(r["time_boot_ms"], r["lat_deg"], r["lon_deg"]) for r in telemetry}
    assert logged <= set(positions)
    dump = subprocess.run([sys.executable, "-m", "pymavlink.tools.mavlogdump", "--types", "MISSION_ITEM_REACHED",
                           str(run_dir(tmp_path) / "mavlink.tlog")], capture_output=True, text=True, timeout=60)
    assert dump.returncode == 0, dump.stderr
    assert dump.stdout.count("MISSION_ITEM_REACHED") == len(items) - 1


def test_link_lost_for_five_seconds_is_logged_and_logging_resumes(start_sitl, start_agent, tmp_path):
    sim = start_sitl(speedup=5.0)
    start_agent(one_agent(sim, tmp_path))
    log_path = run_dir(tmp_path) / "agent.jsonl"
    wait_for_record(log_path, kind("link_up"))
    sim.stop()
    stopped_s = time.time()
    lost = wait_for_record(log_path, kind("link_lost"), timeout_s=5.0)
    time.sleep(max(0.0, stopped_s + 5.0 - time.time()))  # the outage the scenario asks for, not a settle
    start_sitl(config=sim.config)
    restored = wait_for_record(log_path, kind("link_restored"), timeout_s=5.0)
    assert 4.5 < restored["outage_s"] < 8.0
    assert lost["t_s"] < restored["t_s"]
    wait_for_record(log_path, lambda r: r["kind"] == "telemetry" and r["t_s"] > restored["t_s"] + 0.5)
    read = read_jsonl(log_path)
    during = [r for r in read.of_kind("telemetry") if lost["t_s"] < r["t_s"] < restored["t_s"]]
    assert during == [], "no stale positions are logged while the link is down"


def test_tcp_link_is_reopened_after_the_autopilot_restarts(start_sitl, start_agent, tmp_path, base_port):
    sim = start_sitl(speedup=5.0, tcp_base_port=base_port(1) + 5)
    uri = f"tcp:127.0.0.1:{sim.config.tcp_base_port}"
    start_agent(agent_toml("uav1", "master", 1, uri, tmp_path / "runs", free_port(), []))
    log_path = run_dir(tmp_path) / "agent.jsonl"
    wait_for_record(log_path, kind("link_up"))
    sim.stop()
    wait_for_record(log_path, kind("link_lost", why="error"), timeout_s=5.0)
    refused = wait_for_record(log_path, kind("link_open_failed"), timeout_s=5.0)
    assert "refused" in refused["error"]
    start_sitl(config=sim.config)
    wait_for_record(log_path, kind("link_restored"), timeout_s=10.0)
    wait_for_record(log_path, lambda r: r["kind"] == "telemetry" and r["t_s"] > refused["t_s"])


def test_sigkill_mid_write_loses_at_most_the_last_record(start_sitl, start_agent, tmp_path):
    sim = start_sitl(speedup=5.0)
    agent = start_agent(one_agent(sim, tmp_path, log={"telemetry_hz": 500.0, "fsync_s": 0.0}))
    log_path = run_dir(tmp_path) / "agent.jsonl"
    first = wait_for_record(log_path, kind("telemetry"))
    wait_for_record(log_path, lambda r: r["kind"] == "telemetry" and r["t_s"] > first["t_s"] + 0.3)
    os.kill(agent.pid, signal.SIGKILL)  # while it writes 500 records a second
    agent.proc.wait(5)
    read = read_jsonl(log_path)
    assert len(read.of_kind("telemetry")) > 50
    assert not read.of_kind("agent_stopped"), "killed, not stopped"
    damaged = len(read.problems)
    assert damaged == int(read.truncated_tail) <= 1, read.problems
    check = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "log", "check", str(log_path)],
                           capture_output=True, text=True, timeout=30)
    assert f"{len(read.records)} records" in check.stdout
    if read.truncated_tail:
        assert "incomplete" in check.stdout and check.returncode == 1
    else:
        assert check.returncode == 0


def test_two_agents_see_each_other_within_2_s_and_log_peer_lost(start_sitl, start_agent, tmp_path):
    sim = start_sitl(vehicles=2, speedup=5.0, spacing_m=7.0)
    ports = [free_port(), free_port()]
    configs = [agent_toml(f"uav{i + 1}", role, i + 1, companion_uri(sim, i), tmp_path / "runs", ports[i],
                          [ports[1 - i]]) for i, role in enumerate(["master", "worker"])]
    agents = [start_agent(text, name=f"uav{i + 1}") for i, text in enumerate(configs)]
    both_ready_s = max(wait_for_record(run_dir(tmp_path, i) / "agent.jsonl", kind("agent_ready"))["t_s"]
                       for i in range(2))
    for i in range(2):
        seen = wait_for_record(run_dir(tmp_path, i) / "agent.jsonl", kind("peer_seen", peer=f"uav{2 - i}"),
                               timeout_s=3.0)
        assert seen["t_s"] - both_ready_s < 2.0

    # The local state feed serves the compute job both positions; their distance is the simulator's.
    feed = configs[0].split("[state_feed]\nlisten = ")[1].split("\n")[0].strip('"')
    deadline = time.monotonic() + 5.0
    while True:
        state = fetch_state(feed)
        peer = state["peers"].get("uav2", {})
        if peer.get("lat_deg") is not None and state["self"]["lat_deg"] is not None or time.monotonic() > deadline:
            break
    from nac_onboard.agent.state_feed import distance_between

    assert abs(distance_between(state, "uav1", "uav2") - 7.0) < 0.05
    assert peer["role"] == "worker" and peer["age_s"] < 1.0 and not peer["lost"]

    assert agents[1].stop() == 0
    lost = wait_for_record(run_dir(tmp_path, 0) / "agent.jsonl", kind("peer_lost", peer="uav2"), timeout_s=3.0)
    assert lost["silent_s"] >= 1.0, "lost once silent past its 1 s timeout (the record rounds to the millisecond)"
    assert fetch_state(feed)["peers"]["uav2"]["lost"]


def test_a_sped_up_runs_agents_keep_their_peer_period_and_timeout_in_simulated_seconds(start_sitl, start_agent,
                                                                                       tmp_path):
    """On a run's clock at 4x, peer state at 1 Hz is one message a simulated second: 4 a wall second (wall-clock
    periods gave 1, so a sped-up run's air carried a quarter of the peer frames, and a slowed one more). uav2
    counts what it hears from uav1 while both are up: at least 2.5 a wall second is required, a margin of a
    quarter of a second per message for a loaded machine's late wake-ups, where wall periods give at most 1.1. A
    stopped peer is lost once silent for its 2 simulated seconds (0.5 s of wall time) and the record says so in
    simulated seconds: the expiry check every 0.1 s and the last period (0.25 s) make it 2-3.4; wall-clock
    timeouts gave 8 or more."""
    from nac_onboard import clock

    sim = start_sitl(vehicles=2, speedup=4.0)
    clock_path = tmp_path / "clock.json"
    clock.publish(str(clock_path), 4.0, 0.0)
    env = {**os.environ, clock.ENV: str(clock_path)}
    ports = [free_port(), free_port()]
    configs = [agent_toml(f"uav{i + 1}", role, i + 1, companion_uri(sim, i), tmp_path / "runs", ports[i],
                          [ports[1 - i]], peers={"rate_hz": 1.0, "timeout_s": 2.0})
               for i, role in enumerate(["master", "worker"])]
    agents = [start_agent(text, name=f"uav{i + 1}", env=env) for i, text in enumerate(configs)]
    both_ready_s = max(wait_for_record(run_dir(tmp_path, i) / "agent.jsonl", kind("agent_ready"))["t_s"]
                       for i in range(2))
    wait_for_record(run_dir(tmp_path, 1) / "agent.jsonl", kind("peer_seen", peer="uav1"), timeout_s=5.0)
    time.sleep(3.0)  # the window the messages are counted over
    assert agents[1].stop() == 0
    stopped = wait_for_record(run_dir(tmp_path, 1) / "agent.jsonl", kind("agent_stopped"))
    heard_per_wall_s = stopped["peer_msgs"] / (stopped["stop_requested_s"] - both_ready_s)
    assert heard_per_wall_s > 2.5, stopped["peer_msgs"]
    lost = wait_for_record(run_dir(tmp_path, 0) / "agent.jsonl", kind("peer_lost", peer="uav2"), timeout_s=5.0)
    assert 2.0 <= lost["silent_s"] < 4.0, lost


def test_a_slowed_runs_agent_keeps_its_autopilot_link_through_the_slowed_heartbeats(start_sitl, start_agent, tmp_path):
    """At 0.25x the autopilot's 1 Hz heartbeat comes 4 wall seconds apart; the agent's link timeout (3 s here) is
    the run's seconds below 1x, so the link stays up. With the timeout on the wall clock the link was lost and
    restored at every heartbeat (a 16-vehicle fleet at 0.1x logged 2,992 link_lost). Watched over 10 wall seconds
    (two gaps or more); a loaded host only makes the gaps longer, which the wall-clock timeout failed sooner."""
    from nac_onboard import clock

    sim = start_sitl(speedup=0.25)
    clock_path = tmp_path / "clock.json"
    clock.publish(str(clock_path), 0.25, 0.0)
    agent = start_agent(one_agent(sim, tmp_path, autopilot={"link_timeout_s": 3.0}), name="uav1",
                        env={**os.environ, clock.ENV: str(clock_path)})
    log = run_dir(tmp_path) / "agent.jsonl"
    wait_for_record(log, kind("link_up"), timeout_s=10.0)
    time.sleep(10.0)  # heartbeats 4 s apart: the wall-clock timeout lost the link within the first gap
    assert agent.stop() == 0
    kinds_logged = [r["kind"] for r in read_jsonl(log).records]
    assert "agent_stopped" in kinds_logged and "link_lost" not in kinds_logged, kinds_logged


def test_master_probes_each_worker_on_its_period_and_logs_failures_too(start_sitl, start_agent, tmp_path):
    sim = start_sitl(vehicles=2, speedup=5.0, spacing_m=9.0)
    ports = [free_port(), free_port()]
    probing = {"probe": True, "period_s": 1.0, "duration_s": 0.2, "interval_s": 0.1}
    # The master keeps a silent peer for 3 s, so a probe round (every 1 s) falls after the worker has gone.
    configs = [agent_toml("uav1", "master", 1, companion_uri(sim, 0), tmp_path / "runs", ports[0], [ports[1]],
                          throughput=probing, peers={"timeout_s": 3.0}),
               agent_toml("uav2", "worker", 2, companion_uri(sim, 1), tmp_path / "runs", ports[1], [ports[0]])]
    master, worker = (start_agent(text, name=f"uav{i + 1}") for i, text in enumerate(configs))
    log_path = run_dir(tmp_path, 0) / "throughput.jsonl"
    first = wait_for_record(log_path, lambda r: "end" in r and r["distance_m"] is not None, timeout_s=10.0)
    assert (first["client"], first["server"]) == ("uav1", "uav2")
    assert abs(first["distance_m"] - 9.0) < 0.05, "distance between the two GPS positions at probe time"
    assert set(first["positions"]["start"]) == {"uav1", "uav2"}
    assert first["end"]["sum_received"]["bits_per_second"] > 1e6
    assert 1 <= len(first["intervals"]) <= 3, "0.2 s in 0.1 s intervals"
    second = wait_for_record(log_path, lambda r: "end" in r and r["t_s"] > first["t_s"])
    assert 0.8 < second["t_s"] - first["t_s"] < 1.6, "one probe per worker per period_s"

    worker.stop()  # the worker's server goes away before the master notices the peer is lost
    failed = wait_for_record(log_path, lambda r: "error" in r, timeout_s=5.0)
    assert failed["server"] == "uav2" and "uav2" in failed["positions"]["start"]
    assert "cannot connect" in failed["error"]
    assert master.alive()


def test_routing_lets_a_second_tool_share_the_autopilot_link(start_sitl, start_agent, tmp_path):
    """A tool on a routing endpoint arms the vehicle through the agent, and the agent's .tlog holds what it
    relayed: the tool's command and the autopilot's answer (issue 33: "all MAVLink traffic")."""
    sim = start_sitl(speedup=5.0)
    tool_port = free_port()
    tool = mavutil.mavlink_connection(f"udpin:127.0.0.1:{tool_port}", source_system=250)
    try:
        agent = start_agent(one_agent(sim, tmp_path, routing={"endpoints": [f"udpout:127.0.0.1:{tool_port}"]}))
        hb = tool.recv_match(type="HEARTBEAT", blocking=True, timeout=5.0,
                             condition="HEARTBEAT.get_srcComponent() == 1")
        assert hb is not None and hb.get_srcSystem() == 1, "autopilot traffic reaches the routed endpoint"
        for _ in range(3):
            tool.mav.command_long_send(1, 1, MavCmd.COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
            ack = tool.recv_match(type="COMMAND_ACK", blocking=True, timeout=2.0)
            if ack is not None:
                break
        assert ack is not None and ack.result == M.MAV_RESULT_ACCEPTED, "the tool's command reached the autopilot"
        assert sim.truth(0)["armed"]
        assert agent.stop() == 0
    finally:
        tool.close()
    tlog = mavutil.mavlink_connection(str(run_dir(tmp_path) / "mavlink.tlog"))
    logged = []
    while (msg := tlog.recv_match(type=["COMMAND_LONG", "COMMAND_ACK"])) is not None:
        if msg.command == MavCmd.COMPONENT_ARM_DISARM:
            logged.append((msg.get_type(), msg.get_srcSystem()))
    assert ("COMMAND_LONG", 250) in logged, f"the tool's command, as relayed: {logged}"
    assert ("COMMAND_ACK", 1) in logged, f"the autopilot's answer to it: {logged}"


def test_sigterm_and_systemd_notify_and_watchdog(start_sitl, start_agent, tmp_path):
    import socket

    sim = start_sitl(speedup=5.0)
    notify_path = str(tmp_path / "notify.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as notify:
        notify.bind(notify_path)
        notify.settimeout(5.0)
        env = dict(os.environ, NOTIFY_SOCKET=notify_path, WATCHDOG_USEC="400000")
        agent = start_agent(one_agent(sim, tmp_path), env=env)
        received = []
        while received.count("WATCHDOG=1") < 3:
            received += notify.recv(4096).decode().split("\n")
        assert received.index("READY=1") < received.index("WATCHDOG=1")
        assert agent.stop() == 0
        while "STOPPING=1" not in received:
            received += notify.recv(4096).decode().split("\n")
    read = read_jsonl(run_dir(tmp_path) / "agent.jsonl")
    assert read.records[-1]["kind"] == "agent_stopped" and read.records[-1]["reason"] == "SIGTERM"


def test_agent_refuses_bad_config_and_busy_ports_with_clear_errors(tmp_path):
    import socket

    bad = tmp_path / "bad.toml"
    bad.write_text('[vehicle]\nid = "uav1"\nrole = "pilot"\n')
    result = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "agent", "--config", str(bad)],
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 2 and f"{bad}: vehicle.role must be one of master, worker" in result.stderr

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        config = tmp_path / "busy.toml"
        uri = f"udpin:127.0.0.1:{free_port()}"
        config.write_text(agent_toml("uav1", "worker", 1, uri, tmp_path / "runs", port, []))
        result = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "agent", "--config", str(config)],
                                capture_output=True, text=True, timeout=30)
    assert result.returncode == 1 and f"peers.listen: cannot listen on 127.0.0.1:{port}" in result.stderr
    assert "Traceback" not in result.stderr
