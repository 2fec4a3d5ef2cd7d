"""`nac-sitl experiment` end to end: simulator, agents, missions, MPI job and report, on a short sped-up scenario;
its run directory is also what the log analysis and calibration are checked on (a real run, not a fixture)."""

import dataclasses
import io
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from ground import cli as ground_cli
from ground.view.serve import ViewThread
from ground.view.server import ViewServer
from missions import save_mission
from missions.geo import enu_to_lla, lla_to_ecef
from nac_onboard.compute import forestfires, launch
from nac_onboard.flight_log import read_jsonl
from nac_onboard.mavlink.dialect import COPTER_MODES
from nac_onboard.radio.channel import PRESETS
from nac_onboard.radio.files import load_channel, save_channel
from sitl import cli as sitl_cli
from sitl.experiment.commands import run_channel_path
from sitl.experiment.progress import render_progress
from sitl.experiment.runner import Experiment, Outcome
from sitl.experiment.scenario import load_scenario
from sitl.scenarios.generate import at, hover, route
from sitl.vehicle.flight_state import CopterMode
from tests.conftest import SHARED_DATA, allocate_base_port
from tests.integration.conftest import needs_browser
from tests.integration.console import Console, as_at_a_terminal
from tests.integration.test_compute import hydra_teardown

ENV = dict(os.environ, NAC_DATA_DIR=str(SHARED_DATA))
# Logged positions against the truth at 10x, measured rates and per-minute counts: a busy core skews them.
pytestmark = pytest.mark.exclusive
TRUE_EXPONENT = 3.0
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SHORT_RUN_SPEEDUP = 5.0


def write_scenario(folder: Path, duration_s: float = 30.0, extra: str = "") -> Path:
    """Master hovering; w1 flies out from 5 m to 35 m at 2 m/s and w2 hovers 8 m away, over a log-distance
    channel of known exponent (TRUE_EXPONENT) with a small per-transfer overhead so iterations are quick."""
    folder.mkdir(parents=True, exist_ok=True)
    channel = dataclasses.replace(PRESETS["wifi-flight"], name="known", exponent=TRUE_EXPONENT, ref_loss_db=58.0,
                                  shadowing_sigma_db=0.0, rician_k_db=None,
                                  overhead_bits=2e5)
    save_channel(channel, folder / "known.toml")
    save_mission(hover(at(0, 0), 5.0), folder / "master.plan")
    save_mission(route(at(5, 0), 5.0, [(30.0, 0.0)], speed_mps=2.0), folder / "w1.plan")
    save_mission(hover(at(0, 8), 5.0), folder / "w2.plan")
    (folder / "short.toml").write_text(f"""
name = "short"
duration_s = {duration_s}
max_speedup = 10.0
[channel]
preset = "known.toml"
[compute]
task = "linreg"
timeout_s = 2.0
[throughput]
period_s = 0.5
duration_s = 0.2
interval_s = 0.1
[[vehicle]]
id = "master"
role = "master"
mission = "master.plan"
[[vehicle]]
id = "w1"
role = "worker"
mission = "w1.plan"
[[vehicle]]
id = "w2"
role = "worker"
mission = "w2.plan"
""" + extra)
    return folder / "short.toml"


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """One short experiment for the tests below: 30 s simulated at 5x, with the simulator's truth recorded after
    every step: (wall time, positions, simulated time, the master's mode)."""
    folder = tmp_path_factory.mktemp("experiment")
    scenario = load_scenario(str(write_scenario(folder)))
    log_path = folder / "console.txt"
    with pytest.MonkeyPatch.context() as patch, open(log_path, "w") as console:
        patch.setenv("NAC_DATA_DIR", str(SHARED_DATA))
        experiment = Experiment(scenario, folder / "run", SHORT_RUN_SPEEDUP, allocate_base_port(3, slots=5),
                                out=console)
        trace: list = []
        experiment.step_observers.append(lambda t, state: trace.append(
            (time.time(), state.pos_m.copy(), t, int(experiment.sim.world.autopilots.mode[0]))))
        result = experiment.run()
    return result, scenario, trace, log_path.read_text(), experiment


def test_a_short_scenario_runs_end_to_end_and_leaves_a_report(short_run):
    result, scenario, _, console, _ = short_run
    assert result.outcome is Outcome.COMPLETED, console
    run = result.run_dir
    assert "it " in console and "Mbit/s" in console, "the live display shows iterations and throughput"
    for vehicle in ("master", "w1", "w2"):
        agent = read_jsonl(run / vehicle / "agent.jsonl")
        assert agent.problems == [] and agent.records[-1]["kind"] == "agent_stopped"
        assert [r["seq"] for r in agent.of_kind("mission_item_reached")][:1] == [1], "took off on its mission"
    compute = read_jsonl(run / "compute" / "compute.jsonl")
    assert compute.of_kind("run_summary")[0]["ended_by"] == "end_at", "at the scenario's end (the runner's go)"
    assert len(compute.of_kind("iteration")) > 20
    s = result.summary
    assert s["iterations"] > 20 and s["probes"] > 10 and s["final_cost"] < s["first_cost"]
    report = (run / "report.md").read_text()
    assert "speed-up: 5x" in report and "ended: completed" in report
    assert "- probes: nac-onboard's probe, 0.2 s every 0.5 s (40 % of the time), one worker at a time, over this " \
           "host's loopback" in report
    experiment = short_run[4]
    # 0, or hydra's teardown race once the master's summary is written (asserted above), which the job's supervisor
    # and test_compute's judged_exit count as done (SIGPIPE in a clean-clone CI run, 2026-11-29; or 255 with
    # hydra's line saying so, in its mpiexec.log)
    mpi_log = (run / "compute" / "mpiexec.log").read_text(errors="replace")
    assert not any(agent.alive() for agent in experiment.agents)
    assert experiment.mpi.poll() == 0 or hydra_teardown(experiment.mpi.poll(), mpi_log), mpi_log[-2000:]
    assert not experiment.sim.alive, "every part was stopped"
    truth = [experiment.sim.truth(i) for i in range(len(scenario.vehicles))]
    assert all(not t["armed"] and t["pos_m"][2] < 0.1 for t in truth), f"landed and disarmed at the end: {truth}"


def test_mavflightmodes_reads_the_sped_up_runs_tlog_in_simulated_seconds(short_run):
    """The master agent's .tlog of the 5x run is stamped in simulated seconds (issue 33): its AUTO heartbeats span
    the simulated time from the master's switch to AUTO to the agent's stop (the scenario's 30 s and the climb),
    within 1.2 s (the first heartbeat in AUTO comes up to its 1 s period after the switch), not a fifth of it.
    pymavlink's mavflightmodes.py on it says the same, within its own method's error: it times the last mode by the
    share of the file after its start at the bytes per (stamped) second of the mode before, so it is off by the
    ratio of the log's byte rates in AUTO and before it, which the bound takes from this file (a fixed 5 % and 2 s
    once failed a clean-clone run at 38 s against 33.5 s: that run's mission upload had made the stretch before
    AUTO lighter or heavier than usual), plus 2 s for its whole seconds and the first heartbeat's period."""
    from pymavlink import mavutil

    result, scenario, trace, _, experiment = short_run
    tlog = result.run_dir / "master" / "mavlink.tlog"
    agent = read_jsonl(result.run_dir / "master" / "agent.jsonl")
    assert agent.of_kind("agent_started")[0]["tlog_clock"] == "simulated"
    # AUTO from the master's switch to it (its MISSION_START) until the agent was told to stop (the landing after
    # it is not logged), in simulated seconds: that wall time on the simulator's steps. Not the agent_stopped
    # record's own time: it comes after the agent's cleanup, 0.3 wall s (1.6 simulated) late in a loaded CI run.
    wall_s, sim_s = [w for w, *_ in trace], [t for _, _, t, _ in trace]
    stopped_sim_s = np.interp(agent.of_kind("agent_stopped")[0]["stop_requested_s"], wall_s, sim_s)
    flown_s = stopped_sim_s - next(t for _, _, t, mode in trace if mode == CopterMode.AUTO)
    log = mavutil.mavlink_connection(str(tlog))
    stamps, auto_from, share = [], None, {}  # share: the file read (percent) at the first message and at AUTO
    while (msg := log.recv_match()) is not None:
        stamps.append(msg._timestamp)
        share.setdefault("first", log.percent)
        if auto_from is None and msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == 1 \
                and msg.custom_mode == COPTER_MODES["AUTO"]:
            auto_from, share["auto"] = msg._timestamp, log.percent
    assert stamps[-1] - auto_from == pytest.approx(flown_s, abs=1.2), (stamps[-1] - auto_from, flown_s)
    rate_before = (share["auto"] - share["first"]) / (auto_from - stamps[0])  # percent of the file per second
    rate_auto = (100.0 - share["auto"]) / (stamps[-1] - auto_from)

    tool = Path(sys.executable).parent / "mavflightmodes.py"
    done = subprocess.run([str(tool), str(tlog)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    hours, minutes, seconds = re.search(r"^AUTO\s+(\d+):(\d\d):(\d\d)", done.stdout, re.M).groups()
    auto_s = 3600 * int(hours) + 60 * int(minutes) + int(seconds)
    method_error = abs(rate_auto / rate_before - 1.0)
    # the errors add (pytest.approx would take the larger): 28 s against 30.7 with a method error of 3 % (0.9 s)
    # failed a clean-clone run that way, the tool's whole seconds and the first heartbeat's period both shortening it
    assert abs(auto_s - flown_s) <= method_error * flown_s + 2.0, (done.stdout, flown_s, method_error)


@needs_browser
def test_the_view_the_progress_line_and_the_report_give_the_same_pace_and_throughput(short_run, browser):
    """The 5x run read three ways at its end: report.md (and its throughput table), the runner's progress line
    (rendered from the finished run) and the replayed view (job panel, link labels). Iterations per simulated
    minute agree within 1 %, each worker's last probe within 1 % or the view's 0.1 Mbit/s display (issue 33).
    Nothing here is timed: the three read the same records."""
    from tests.integration.test_view import wait_for

    result, scenario, *_ = short_run
    run = result.run_dir
    report = (run / "report.md").read_text()
    report_pace = float(re.search(r"\| iterations per minute \| ([\d.]+) \|", report)[1])
    assert report_pace == pytest.approx(result.summary["iterations_per_min"], rel=1e-3)
    probes = pd.read_csv(run / "analysis" / "throughput.csv").dropna(subset=["throughput_mbps"])
    last_mbps = {w: float(probes[probes["server"] == w]["throughput_mbps"].iloc[-1]) for w in ("w1", "w2")}

    line = render_progress(scenario.duration_s, [], run, "master")
    pace = re.search(r"it (\d+), ([\d.]+)/min", line)
    assert pace and float(pace[2]) == pytest.approx(report_pace, rel=0.01), (line, report_pace)
    assert int(pace[1]) == result.summary["iterations"]
    probe = re.search(r"\| (w\d): ([\d.]+) Mbit/s", line)
    assert probe and float(probe[2]) == pytest.approx(last_mbps[probe[1]], rel=0.01, abs=0.05), (line, last_mbps)

    viewer = ViewThread(ViewServer(run, live=False), "127.0.0.1:0")
    browser.get(viewer.start() + "?at=end")  # the run's last record: a slider's 0.1 s steps could stop short of it
    try:
        wait_for(browser, "return document.body.dataset.ready")
        job = browser.execute_script("return document.getElementById('job').textContent")
        labels = browser.execute_script("return Object.fromEntries([...document.querySelectorAll('#links line')]"
                                        ".map((l, k) => [l.dataset.worker, "
                                        "document.querySelectorAll('#links .link-label')[k].textContent]))")
    finally:
        viewer.stop()
    count, view_pace = re.search(r"(\d+) iterations, (\d+) per minute", job).groups()
    assert int(count) == result.summary["iterations"]
    assert float(view_pace) == pytest.approx(report_pace, rel=0.01), (job, report_pace)
    for worker, mbps in last_mbps.items():
        shown = re.match(r"([\d.]+) Mbit/s", labels[worker])
        assert shown and float(shown[1]) == pytest.approx(mbps, rel=0.01, abs=0.05), (worker, labels, last_mbps)


def test_analysis_of_the_run_matches_the_simulators_truth(short_run):
    result, scenario, trace, _, _ = short_run
    analysis = result.run_dir / "analysis"
    columns = {"distances": "t_s,t_rel_s,worker,distance_m",
               "throughput_by_distance": "distance_from_m,distance_to_m,mean_mbps,std_mbps,p2_5_mbps,p97_5_mbps,count",
               "iterations": "iteration,t_s,t_rel_s,start_sim_s,duration_s,complete,workers_present,absent,cost",
               "training_cost": "iteration,t_rel_s,elapsed_s,cost"}
    for name, header in columns.items():
        assert (analysis / f"{name}.csv").read_text().splitlines()[0] == header
    for png in analysis.glob("*.png"):
        data = png.read_bytes()
        assert data[:8] == PNG_MAGIC and 10_000 < len(data) < 2_000_000, png.name
    assert len(list(analysis.glob("*.png"))) == 8, "seven figures and the power the run metered"

    # the truth: every vehicle's ECEF position after each simulator step, by wall-clock time
    homes = [v.home for v in scenario.vehicles]
    times = np.array([t for t, *_ in trace])
    ecef = np.array([[lla_to_ecef(*enu_to_lla(pos[i], homes[i])) for i in range(3)] for _, pos, *_ in trace[::5]])
    times = times[::5]
    distances = pd.read_csv(analysis / "distances.csv")
    assert set(distances["worker"]) == {"w1", "w2"} and len(distances) > 100
    errors = []
    for row in distances.itertuples():
        k = 1 if row.worker == "w1" else 2
        true = [np.interp(row.t_s, times, np.linalg.norm(ecef[:, 0, :] - ecef[:, k, :], axis=1))]
        errors.append(abs(row.distance_m - true[0]))
    # Rows are stamped when the agents hear the telemetry: at 5x, w1's 2 m/s is 10 m per wall-clock second, so a
    # record 60 ms late on a loaded machine is 0.6 m off (at 4x: 99 % within 0.2 m, two runs had one row 65 ms
    # late). Nearly every row at most 60 ms late, none beyond 120 ms.
    late_m = 2.0 * SHORT_RUN_SPEEDUP * 0.06
    assert np.percentile(errors, 99) < late_m and max(errors) < 2 * late_m, \
        f"distances from the truth: 99th percentile {np.percentile(errors, 99):.2f} m, worst {max(errors):.2f} m"
    w1 = distances[distances["worker"] == "w1"]["distance_m"]
    assert w1.min() < 6.0 and w1.max() > 30.0, "the comparison covers w1's whole flight out"


def test_calibrate_recovers_the_channel_the_run_was_made_with(short_run, tmp_path):
    result, scenario, _, _, _ = short_run
    preset = tmp_path / "fitted.toml"
    out = io.StringIO()
    args = ground_cli.build_parser().parse_args(["logs", "calibrate", str(result.run_dir), "--base",
                                                 str(run_channel_path(result.run_dir)), "--out", str(preset)])
    assert ground_cli.run(args, out) == 0
    fitted = load_channel(str(preset))
    # The run's link has no shadowing: most probes sit at three places (w2 hovering, w1 before and after its
    # flight), so one shadowing draw each would tilt the fit; recovery from shadowed, faded probes is checked
    # on model-made ones at independent places (tests/unit/test_log_analysis.py).
    assert fitted.exponent == pytest.approx(TRUE_EXPONENT, rel=0.10)
    assert fitted.path_loss == "log-distance" and fitted.name == "calibrated-run"
    text = out.getvalue()
    assert "95 %" in text and "residuals" in text and "shadowing sigma" in text, text
    assert preset.with_suffix(".png").read_bytes().startswith(PNG_MAGIC)


def test_a_scheduled_fault_happens_and_the_job_trains_on_when_a_companion_pack_runs_out(tmp_path):
    """w2's autopilot link goes down and comes back (a scheduled fault). w1's companion pack holds 1.8 mAh, some
    12 simulated seconds of its computer and radio: when it is empty, w1's agent and rank stop and the job trains on
    with w2. The report's energy table gives each vehicle the integral of the power it recorded, within 1 %."""
    faults = """
[[fault]]
at_s = 3.0
vehicle = "w2"
kind = "link_down"
duration_s = 18.0  # 4.5 s wall-clock at 4x: longer than the agent's 3 s link timeout
"""
    path = write_scenario(tmp_path / "scenario", extra=faults)
    path.write_text(path.read_text().replace('id = "w1"\n', 'id = "w1"\ncompanion_mah = 1.8\n'))
    scenario = load_scenario(str(path))
    console = io.StringIO()
    experiment = Experiment(scenario, tmp_path / "run", 4.0, allocate_base_port(3, slots=5), out=console,
                            figures=False)
    result = experiment.run()
    assert result.outcome is Outcome.COMPLETED, console.getvalue()
    text = console.getvalue()
    assert "fault: link_down on for w2" in text and "fault: link_down off for w2" in text
    assert "w1's companion pack is empty" in text and "fault: lose_companion on for w1" in text
    w2 = read_jsonl(result.run_dir / "w2" / "agent.jsonl")
    assert w2.of_kind("link_lost") and w2.of_kind("link_restored"), "the agent saw its autopilot link go and return"
    compute = read_jsonl(result.run_dir / "compute" / "compute.jsonl")
    summary = compute.of_kind("run_summary")[0]
    assert summary["ended_by"] == "end_at", "the job ran to the end"
    killed_at = experiment.mission_start_sim_s + next(r["t_sim_s"] for r in experiment.fault_log
                                                      if r["kind"] == "lose_companion")
    after = [r for r in compute.of_kind("iteration") if r["start_sim_s"] > killed_at + 5.0]
    assert after and all(r["workers"]["present"][1] for r in after), "w2 kept training"
    assert {r["workers"]["absent"][0] for r in after} <= {"agent_lost", "unresponsive"}, "w1 lost, and known lost"
    assert (result.run_dir / "compute" / "results.npz").exists()
    report = (result.run_dir / "report.md").read_text()
    assert "ended: completed" in report and "## Energy" in report
    assert not any(agent.alive() for agent in experiment.agents) and not experiment.sim.alive

    energy = read_jsonl(result.run_dir / "energy.jsonl")
    (empty,) = energy.of_kind("battery_empty")
    assert empty["vehicle"] == "w1" and empty["stopped"] == ["agent", "rank"]
    assert 6.0 < empty["t_sim_s"] < 20.0, "1.8 mAh: some 12 s of an idling companion"
    table = pd.read_csv(result.run_dir / "analysis" / "energy_by_vehicle.csv").set_index("vehicle")
    for vehicle in ("master", "w1", "w2"):
        records = [r for r in energy.of_kind("energy") if r["vehicle"] == vehicle]
        assert records[-1]["t_sim_s"] > 28.0, "recorded to the scenario's end"
        recorded_wh = sum((r["flight_w"] + r["companion_w"]) * r["dt_s"] for r in records) / 3600.0
        assert table.loc[vehicle, "total_wh"] == pytest.approx(recorded_wh, rel=0.01)
        assert all(r["flight_w"] > 100.0 for r in records[3:]), "flying: Zeng's rotorcraft draws 229 W in hover"
    assert table.loc["w1", "companion_soc_end"] == 0.0 < table.loc["w2", "companion_soc_end"]
    after_empty = [r for r in energy.of_kind("energy") if r["vehicle"] == "w1" and r["t_sim_s"] > empty["t_sim_s"]]
    assert after_empty and all(r["companion_w"] == 0.0 for r in after_empty), "an empty pack gives nothing"


def test_sigterm_stops_everything_within_10_s_exits_143_and_writes_a_partial_report(tmp_path):
    """`kill`, `timeout` and systemd's stop send SIGTERM: it once went unnoticed and the run went on to "completed".
    Now it is Ctrl-C with its own exit code (Ctrl-C itself: test_kernel_network.py, the same path)."""
    console, run = stop_a_running_experiment(tmp_path, signal.SIGTERM, exit_code=143)
    assert "terminated (SIGTERM)" in console.text()
    report = (run / "report.md").read_text()
    assert "ended: terminated" in report and "iterations done" in report


def test_sigkill_leaves_nothing_of_the_run_running_within_10_s(tmp_path):
    """SIGKILL runs no clean-up: its agents and MPI job once ran on (an orphaned master agent probed for 36
    minutes). Its children now die with it (parent-death signal) and its watchdog kills the rest (the ranks, in
    sessions of their own)."""
    stop_a_running_experiment(tmp_path, signal.SIGKILL, exit_code=-signal.SIGKILL)


def stop_a_running_experiment(tmp_path: Path, signum: int, exit_code: int) -> tuple[Console, Path]:
    """Start the short scenario for 600 s, wait for the MPI job to compute, send signum to the runner alone: every
    process it started (its watchdog, agents, mpiexec, the ranks) must be gone within 10 s, and the runner must
    end with exit_code (after its partial report, whose analysis alone can take 10 s on a loaded machine: 60 s).
    The 10 s bound holds on a loaded 2-core machine: the runner stops its agents with SIGTERM (milliseconds each)
    and the MPI job's session (SIGKILL after 5 s); after SIGKILL the kernel delivers the parent-death signals at
    once and the watchdog needs one pass over /proc. Nor may MPI's files stay behind (its proxies' topology files in
    /tmp, its ranks' shared memory in /dev/shm, which die with mpiexec without removing them). Returns the runner's
    console and run directory."""
    scenario = write_scenario(tmp_path / "scenario", duration_s=600.0)
    run = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "sitl.cli", "experiment", str(scenario), "--speedup", "4",
                             "--network", "sleep",
                             "--out", str(run), "--base-port", str(allocate_base_port(3, slots=5))],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV,
                            preexec_fn=as_at_a_terminal)
    console = Console(proc, "MPI job started")
    try:
        assert console.seen.wait(60.0), console.text()
        compute_log = run / "compute" / "compute.jsonl"
        deadline = time.monotonic() + 30.0
        while not (compute_log.exists() and '"iteration"' in compute_log.read_text()):
            assert time.monotonic() < deadline, console.text()
            time.sleep(0.1)
        pids = children_of(proc.pid)
        assert len(pids) >= 7, "the watchdog, agents, mpiexec and the ranks are running"
        held = launch.mpi_scratch_files(pids)  # a topology file per MPI proxy, a shared-memory segment per rank
        assert len(held) == 6, held
        proc.send_signal(signum)
        left = wait_for_none_alive(pids, timeout_s=10.0)
        assert left == [], f"left running 10 s after {signal.Signals(signum).name}: {left}"
        assert [f for f in held if Path(f).exists()] == [], "MPI's files are left behind"
        assert proc.wait(60.0) == exit_code, console.text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    console.join()
    return console, run


def wait_for_none_alive(pids: list[int], timeout_s: float) -> list[int]:
    """The pids still alive (zombies count as gone) once none is, or when timeout_s has passed."""
    deadline = time.monotonic() + timeout_s
    while True:
        alive = [pid for pid in pids if Path(f"/proc/{pid}").exists() and "Z" not in status_of(pid)]
        if not alive or time.monotonic() >= deadline:
            return alive
        time.sleep(0.05)


def children_of(pid: int) -> list[int]:
    """Every descendant of pid (agents, mpiexec and its ranks, in their own session)."""
    out = subprocess.run(["ps", "-e", "-o", "pid=,ppid="], capture_output=True, text=True).stdout
    parent = {int(a): int(b) for a, b in (line.split() for line in out.splitlines())}
    found, frontier = [], {pid}
    while frontier:
        frontier = {p for p, pp in parent.items() if pp in frontier}
        found += frontier
    return found


def status_of(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2]
    except OSError:
        return "Z"


def test_a_taken_port_or_missing_data_fails_the_run_with_a_sentence(tmp_path, monkeypatch):
    scenario = load_scenario(str(write_scenario(tmp_path / "scenario")))
    base = allocate_base_port(3, slots=5)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as squatter:
        squatter.bind(("127.0.0.1", base + 2))  # where the master's agent listens for its peers
        result = Experiment(scenario, tmp_path / "run", 4.0, base, out=io.StringIO()).run()
    assert result.outcome is Outcome.AGENT_FAILED and result.outcome.exit_code == 1
    assert "master: " in result.detail and str(base + 2) in result.detail, result.detail

    monkeypatch.setenv("NAC_DATA_DIR", str(tmp_path / "empty"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setattr(forestfires, "SOURCE_CHECKOUT_DATA", tmp_path / "not-a-checkout")
    t0 = time.monotonic()
    result = Experiment(scenario, tmp_path / "run2", 4.0, base, out=io.StringIO()).run()
    assert result.outcome is Outcome.BAD_INPUT and result.outcome.exit_code == 2
    assert "Forest Fires CSV not found" in result.detail and time.monotonic() - t0 < 5.0


def test_a_recorded_run_replays_its_links_on_the_kernel_network(short_run, tmp_path):
    """The short run's probes (recorded on the sleep network) drive the kernel shaper of a second run of the same
    scenario: the rates applied are the recording's, interpolated, and what the second run's probes measure
    matches the recorded throughput at the same simulated times within 10 % (median)."""
    from sitl.network.netns import NetworkUnavailable, check_kernel_network
    from sitl.network.replay import replay_from_run

    try:
        check_kernel_network()
    except NetworkUnavailable as err:
        pytest.skip(str(err))
    result, scenario, _, _, _ = short_run
    replay = replay_from_run(result.run_dir)
    assert set(replay.series) == {("master", "w1"), ("master", "w2")}
    with open(tmp_path / "console.txt", "w") as console:
        replayed = Experiment(scenario, tmp_path / "replayed", 4.0, allocate_base_port(3, slots=5), out=console,
                              network=("kernel", "test"), replay=replay, figures=False).run()
    assert replayed.outcome is Outcome.COMPLETED, replayed.detail
    run = replayed.run_dir
    updates = read_jsonl(run / "network.jsonl").of_kind("link_rates")
    assert updates and all(u["source"] == f"replay:{result.run_dir}" for u in updates)
    applied, recorded = [], []
    for u in updates:
        k = u["b"].index("w1") if u["a"][0] == "master" else None
        if k is None or u["rate_bps"][k] < 2e6:
            continue
        applied.append(u["rate_bps"][k])
        recorded.append(replay.rate_bps("master", "w1", u["t_sim_s"]))
    assert applied and np.allclose(applied, recorded, rtol=1e-3, atol=1.0), "the shaper applies the recording"
    ratios = []
    for probe in read_jsonl(run / "master" / "throughput.jsonl").of_kind("throughput"):
        was = replay.rate_bps(probe["client"], probe["server"], probe["t_sim_s"])
        got = (probe.get("end") or {}).get("sum_received", {}).get("bits_per_second")
        if got and was and was > 2e6:
            ratios.append(got / probe["speedup"] / was)
    assert len(ratios) > 20
    assert np.median(ratios) == pytest.approx(1.0, abs=0.10), sorted(ratios)
    assert "replay:" in (run / "experiment.json").read_text()


def test_on_the_sleep_network_the_replay_table_reaches_every_process(short_run, tmp_path):
    """A sleep-network run with --links replay: the runner writes the table beside the run's channel, and the
    channel every process loads gives the recorded rates; unknown vehicles or a missing run are refused."""
    from nac_onboard.clock import Clock
    from nac_onboard.link.emulation import SleepEmulation
    from sitl.network.replay import replay_from_run

    result, scenario, _, _, _ = short_run
    replay = replay_from_run(result.run_dir)
    experiment = Experiment(scenario, tmp_path / "replayed", 4.0, 14550, out=io.StringIO(),
                            network=("sleep", "test"), replay=replay)
    experiment._write_channel()
    channel = load_channel(str(run_channel_path(experiment.run_dir)))
    assert experiment.scenario is scenario and channel == experiment.radio, "one radio, written once"
    assert channel.replay_file == str(tmp_path / "replayed" / "config" / "replay.json")

    class At(Clock):
        def now_s(self) -> float:
            return 20.0

    emulation = SleepEmulation(channel, At())
    link = emulation.link(12.0, 1, ("master", "w1"))
    assert link.capacity_bps == pytest.approx(replay.rate_bps("master", "w1", 20.0))
    assert emulation.link(12.0, 2, ("w1", "w2")).capacity_bps != link.capacity_bps, "unrecorded: the model"
    other = dataclasses.replace(scenario, vehicles=scenario.vehicles[:2])
    refused = Experiment(other, tmp_path / "r", 4.0, 14550, out=io.StringIO(), analyze=False, replay=replay).run()
    assert refused.outcome is Outcome.BAD_INPUT and "w2" in refused.detail
    assert sitl_cli.main(["experiment", str(scenario.path), "--links", f"replay:{tmp_path / 'nothing'}"]) == 2
