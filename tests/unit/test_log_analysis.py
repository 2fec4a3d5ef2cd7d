"""Log analysis on files (no processes): the golden run's known numbers, damaged input, the autopilot-log readers
and the path-loss fit."""

import copy
import dataclasses
import io
import json
import shutil
import struct
from pathlib import Path

import matplotlib.image
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
import pytest

from ground import cli
from ground.logs import figures
from ground.logs.analysis import analyze
from ground.logs.autopilot_logs import dataflash_positions, read_tlog, tlog_positions, ulog_positions
from ground.logs.calibration import CalibrationError, fit_channel
from ground.logs.findings import beside_the_research, research_findings
from ground.logs.report import _probes_line, analyze_run
from ground.logs.runlog import read_run
from nac_onboard.flight_log import JsonlLog, TlogWriter
from nac_onboard.mavlink.dialect import M
from nac_onboard.radio.air_link import Radio
from nac_onboard.radio.channel import PRESETS
from nac_onboard.records import kinds
from tests.conftest import SHARED_DATA
from tests.logfiles import write_dataflash, write_ulog

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced

GOLDEN = Path(__file__).parents[1] / "data" / "golden-run"


def rows(table, digits: int = 6) -> list[list]:
    return [[round(v, digits) if isinstance(v, float) else v for v in row] for row in table.itertuples(index=False)]


def test_golden_run_gives_exactly_the_known_tables():
    t = analyze(read_run(GOLDEN))
    assert t.master == "master" and t.t0_s == 1000.0
    # w1 flies east at 2 m/s from 10 m; its samples are 0.05 s late, so at the master's whole seconds it is at
    # 10 + 2 * (k - 0.05): the t=0 sample is before w1's first and is left out, not extrapolated.
    assert rows(t.distances[["t_rel_s", "worker", "distance_m"]], 3) == [  # positions are stored to 0.1 mm
        [1.0, "w1", 11.9], [2.0, "w1", 13.9], [3.0, "w1", 15.9], [4.0, "w1", 17.9]]
    assert len(t.trajectories[t.trajectories["vehicle"] == "w1"]) == 5, "the repeated sample counted once"
    assert rows(t.throughput[["t_rel_s", "distance_m", "throughput_mbps", "error"]]) == [
        [0.0, 3.0, 40.0, ""], [1.0, 3.5, 60.0, ""], [2.0, 5.0, 30.0, ""], [3.0, 9.0, 10.0, ""],
        [4.0, 9.5, 20.0, ""], [5.0, 21.0, 0.0, "unable to connect to server: timed out"]]
    assert rows(t.throughput_by_distance) == [
        [2.0, 4.0, 50.0, round(np.sqrt(200), 6), 40.5, 59.5, 2], [4.0, 6.0, 30.0, 0.0, 30.0, 30.0, 1],
        [8.0, 10.0, 15.0, round(np.sqrt(50), 6), 10.25, 19.75, 2], [20.0, 22.0, 0.0, 0.0, 0.0, 0.0, 1]]
    assert rows(t.iterations[["iteration", "t_rel_s", "duration_s", "workers_present", "absent", "cost"]]) == [
        [0, 1.0, 0.5, 2, "", 10.0], [1, 1.5, 0.5, 2, "", 8.0], [2, 2.0, 1.0, 1, "w2:out_of_range", 7.0],
        [3, 3.0, 0.5, 2, "", 6.5]]
    assert rows(t.training_cost) == [[0, 1.0, 0.0, 10.0], [1, 1.5, 0.5, 8.0], [2, 2.0, 1.0, 7.0], [3, 3.0, 2.0, 6.5]]
    s = t.summary
    assert (s["iterations"], s["mean_iteration_s"], s["compute_span_s"], s["iterations_per_min"]) == (4, 0.625, 2.5,
                                                                                                        96.0)
    assert s["p95_iteration_s"] == pytest.approx(0.925)
    assert s["absent_iterations"] == {"w2": 1} and s["failed_probes"] == 1
    assert s["range_above_threshold_m"] == 10.0, "bins up to 8-10 m stay above 1 Mbit/s; 20-22 m is at 0"
    assert t.missing == [] and t.problems == []


def test_a_sped_up_sitl_runs_tables_are_on_its_simulated_clock(tmp_path):
    """The golden run as if flown at 4x: its shaper's records pair each wall second with four simulated ones (from
    1000.5 to 1003 only: before and after, the run's mean pace), so every table's t_rel_s is four times the wall
    offset, as the same flight at 1x would read; without such records (the golden run as is) it stays wall time."""
    run = tmp_path / "run"
    shutil.copytree(GOLDEN, run)
    link = {"kind": "link_rates", "speedup": 4.0, "a": ["master"], "b": ["w1"], "distance_m": [10.0],
            "rate_bps": [1e7], "loss": [0.0], "snr_db": [20.0], "mcs": [3], "source": "wifi-flight"}
    records = [{"t_s": 1000.0, "kind": "schema", "schema_version": 1, "file": "network.jsonl"}] + [
        {"t_s": 1000.5 + k * 0.25, **link, "t_sim_s": 2.0 + k} for k in range(11)]
    (run / "network.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    t = analyze(read_run(run))
    assert t.clock.simulated and t.t0_s == 1000.0
    assert rows(t.distances[["t_rel_s", "distance_m"]], 3) == [[4.0, 11.9], [8.0, 13.9], [12.0, 15.9], [16.0, 17.9]]
    assert t.throughput["t_rel_s"].tolist() == [0.0, 4.0, 8.0, 12.0, 16.0, 20.0]
    assert t.iterations["t_rel_s"].tolist() == [4.0, 6.0, 8.0, 12.0]
    assert t.training_cost["elapsed_s"].tolist() == [0.0, 2.0, 4.0, 8.0]
    assert not analyze(read_run(GOLDEN)).clock.simulated


def test_a_fault_before_the_first_iteration_has_none_in_the_table_and_is_marked_at_the_first_on_the_figure(tmp_path):
    """A slow MPI start (a loaded machine) can leave a fault before any iteration: the events table says no iteration
    ran then, and the cost figure still marks it, at the first iteration; a fault during iteration 2 is at 2."""
    run = tmp_path / "run"
    shutil.copytree(GOLDEN, run)
    log = JsonlLog(run / "experiment.json", t_s=999.0)
    for t_s, state in ((1000.2, "on"), (1002.5, "off")):
        log.write(kinds.FAULT, t_s, vehicle="w1", fault="reboot_companion", state=state, t_sim_s=t_s - 1000.0)
    log.close()
    t = analyze(read_run(run))
    assert t.events["what"].tolist() == ["reboot_companion on: w1", "reboot_companion off: w1"]
    assert t.events["iteration"].isna().tolist() == [True, False] and t.events["iteration"].iloc[1] == 2
    fig, ax = plt.subplots()
    figures.training_cost(ax, t)
    assert sorted(line.get_xdata()[0] for line in ax.lines[1:]) == [0, 2], "one mark per fault, at 0 and 2"
    plt.close(fig)


def test_analyze_writes_tables_figures_and_a_report(tmp_path):
    out = tmp_path / "out"
    assert cli.main(["logs", "analyze", str(GOLDEN), "--out", str(out)]) == 0
    for name in ("distances", "throughput", "throughput_by_distance", "iterations", "training_cost", "trajectories"):
        assert (out / f"{name}.csv").stat().st_size > 0
    report = (out / "report.md").read_text()
    for figure in ("trajectories", "distances", "throughput_over_time", "throughput_vs_distance", "iteration_time",
                   "time_per_10_vs_distance", "training_cost"):
        png = (out / f"{figure}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
        assert f"]({figure}.png)" in report


def test_damaged_and_missing_input_is_named_not_raised(tmp_path, caplog):
    run = tmp_path / "run"
    shutil.copytree(GOLDEN, run)
    shutil.rmtree(run / "compute")
    with open(run / "w1" / "agent.jsonl", "a") as f:
        f.write('{"t_s": 1010.0, "kind": "telem')  # the agent was killed mid-record
    (run / "w3").mkdir()
    (run / "w3" / "agent.jsonl").write_text('{"t_s": 999.0, "kind": "agent_started", "role": "worker"}\n')
    t = analyze_run(run)
    assert any("w1/agent.jsonl: line 9: last record is incomplete" in p for p in t.problems)
    assert "line 9" in caplog.text
    assert "vehicle w3: no positions (no telemetry records and no autopilot log)" in t.missing
    assert "compute: no iteration records (compute.jsonl)" in t.missing
    report = (run / "analysis" / "report.md").read_text()
    assert "vehicle w3: no positions" in report and "no compute iterations in this run" not in report
    assert len(t.distances) == 4, "the intact records are all used"


def test_a_reanalysis_replaces_the_runs_own_report_and_leaves_no_second_one(tmp_path, capsys):
    run = tmp_path / "flight-3"
    shutil.copytree(GOLDEN, run)
    (run / "report.md").write_text("the experiment runner's report\n")
    assert cli.main(["logs", "analyze", str(run)]) == 0
    assert (run / "report.md").read_text().startswith("# flight-3: a NAC run\n")
    assert not (run / "analysis" / "report.md").exists() and (run / "analysis" / "distances.csv").is_file()
    assert capsys.readouterr().out.startswith(f"{run / 'report.md'}: ")


def test_a_comparison_draws_both_runs_iteration_time_distributions_on_one_axes(tmp_path):
    """The distribution figure is the comparison's own (one axes, both runs, matplotlib's first and second colours):
    the golden run's curve is drawn and a run without iterations is said to have none, not drawn; the figure is
    linked from the report."""
    without = tmp_path / "without-compute"
    shutil.copytree(GOLDEN, without)
    shutil.rmtree(without / "compute")
    out = tmp_path / "cmp"
    assert cli.main(["logs", "compare", str(GOLDEN), str(without), "--out", str(out)]) == 0
    png = out / "iteration_time_distribution.png"
    assert "](iteration_time_distribution.png)" in (out / "report.md").read_text()
    image = matplotlib.image.imread(png)
    red, green, blue = image[..., 0], image[..., 1], image[..., 2]
    first = (red < 0.2) & (green > 0.4) & (green < 0.6) & (blue > 0.6)  # tab:blue, the golden run
    second = (red > 0.9) & (green > 0.4) & (green < 0.6) & (blue < 0.2)  # tab:orange
    assert first.sum() > 50 and second.sum() == 0


def test_an_empty_or_missing_directory_is_exit_2_with_a_sentence(tmp_path, capsys):
    assert cli.main(["logs", "analyze", str(tmp_path)]) == 2
    assert "no NAC logs here" in capsys.readouterr().err
    assert cli.main(["logs", "analyze", str(tmp_path / "nope")]) == 2
    assert "no such run directory" in capsys.readouterr().err


def write_positions_tlog(path: Path, n: int, junk_every: int = 0) -> list[tuple]:
    """A .tlog of n GLOBAL_POSITION_INT (with HEARTBEATs between) written through pymavlink's own encoder."""
    mav = M.MAVLink(io.BytesIO(), srcSystem=3, srcComponent=1)
    expected = []
    with open(path, "wb") as f:
        for k in range(n):
            t_s = 1_700_000_000.0 + k * 0.1
            lat, lon = 473977420 + 10 * k, 85455940 - 7 * k
            for msg in (M.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3),
                        M.MAVLink_global_position_int_message(100 * k, lat, lon, 500_000 + k, 10_000, 0, 0, 0, 0)):
                f.write(struct.pack(">Q", int(t_s * 1e6)) + msg.pack(mav))
            if junk_every and k % junk_every == 0:
                f.write(b"\x00\x13garbage\xfd\x05")
            expected.append((round(t_s, 6), lat / 1e7, lon / 1e7, (500_000 + k) / 1000))
    return expected


def test_tlogs_from_the_agent_and_from_pymavlink_give_the_same_positions(tmp_path):
    expected = write_positions_tlog(tmp_path / "pymavlink.tlog", 50)
    # the agent's writer: the same frames, its own stamps
    frames = read_tlog(tmp_path / "pymavlink.tlog", wanted=("GLOBAL_POSITION_INT", "HEARTBEAT"))
    writer = TlogWriter(tmp_path / "agent.tlog")
    for t_s, msg in frames.messages:
        writer.write(msg.get_msgbuf(), t_s)
    writer.close()
    for name in ("pymavlink.tlog", "agent.tlog"):
        got, problems = tlog_positions(tmp_path / name, "uav3")
        assert problems == []
        assert [(round(r["t_s"], 6), r["lat_deg"], r["lon_deg"], r["alt_m"]) for r in got] == expected
        assert {r["vehicle"] for r in got} == {"uav3"}


def test_tlog_corruption_is_skipped_and_counted(tmp_path):
    path = tmp_path / "damaged.tlog"
    expected = write_positions_tlog(path, 40, junk_every=10)
    data = bytearray(path.read_bytes())
    data[300] ^= 0xFF  # one bit-flipped byte inside a frame: its checksum fails
    path.write_bytes(bytes(data) + b"\x00\x00\x01")  # and a cut-off last record
    read = read_tlog(path)
    assert read.skipped_bytes == 4 * 11 and read.truncated_tail
    assert read.bad_crc + len(read.messages) == 40 and read.bad_crc <= 1
    assert len(read.problems) == 2 + (read.bad_crc > 0) and "corrupt bytes skipped" in read.problems[0]
    got = {round(t, 6) for t, _ in read.messages}
    assert got <= {e[0] for e in expected} and len(got) >= 39


def test_dataflash_and_ulog_positions_on_unix_time(tmp_path):
    boot = 1_700_000_000.25
    samples = [(boot + 10 + 0.2 * k, 47.3977419 + 1e-5 * k, 8.5455938 - 1e-5 * k, 488.25 + k) for k in range(5)]
    write_dataflash(tmp_path / "flight.bin", samples, boot)
    write_ulog(tmp_path / "flight.ulg", samples, boot)
    for reader, path in ((dataflash_positions, "flight.bin"), (ulog_positions, "flight.ulg")):
        got, problems = reader(tmp_path / path, "uav1")
        assert problems == []
        assert len(got) == 5
        for row, (t_s, lat, lon, alt) in zip(got, samples, strict=True):
            assert row["t_s"] == pytest.approx(t_s, abs=1e-3)
            assert (row["lat_deg"], row["lon_deg"]) == pytest.approx((lat, lon), abs=1e-7)
            assert row["alt_m"] == pytest.approx(alt, abs=0.01)


def test_a_vehicle_with_only_an_autopilot_log_gets_positions_from_it(tmp_path):
    run, t0 = tmp_path / "run", 1_700_000_000.0
    (run / "master").mkdir(parents=True)
    (run / "w1").mkdir()
    records = [{"t_s": t0, "kind": "agent_started", "role": "master"}] + [
        {"t_s": t0 + k, "kind": "telemetry", "time_boot_ms": 1000 * k, "lat_deg": 47.0, "lon_deg": 8.0, "alt_m": 510}
        for k in range(5)]
    (run / "master" / "agent.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    write_dataflash(run / "w1" / "00000001.bin", [(t0 + k, 47.0, 8.0001 + 1e-5 * k, 510.0) for k in range(5)], t0 - 10)
    t = analyze(read_run(run))
    w1 = t.trajectories[t.trajectories["vehicle"] == "w1"]
    assert len(w1) == 5 and w1["t_rel_s"].tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert np.allclose(np.diff(t.distances["distance_m"]), 0.7606, atol=1e-3), "1e-5 deg of longitude at 47 N"


def test_calibration_recovers_path_loss_and_shadowing_from_probes_the_model_made():
    """600 one-second probes on moving links at 3-35 m (each probe a new place: its own shadowing; 20 fades
    averaged), some at nothing and some at the top rate, fitted with the preset as the base radio."""
    base = PRESETS["wifi-flight"]
    true = dataclasses.replace(base, exponent=3.2, ref_loss_db=52.0, shadowing_sigma_db=4.0)
    rng = np.random.default_rng(0)
    d = rng.uniform(3, 35, 600)
    r = Radio(true, len(d), seed=100)
    r.step(0.0, d)
    rate = np.mean([r.step(0.1, d, moved_m=np.zeros(len(d)), speed_mps=np.full(len(d), 1.34)).goodput_bps
                    for _ in range(20)], axis=0)
    fit = fit_channel(d, rate, base, samples_per_probe=20)
    assert fit["censored_low"] > 0 and fit["censored_high"] > 0
    assert fit["exponent"] == pytest.approx(3.2, rel=0.10)
    assert fit["ref_loss_db"] == pytest.approx(52.0, rel=0.10)
    assert fit["sigma_db"] == pytest.approx(4.0, rel=0.10)
    assert fit["exponent_ci"][0] < fit["exponent"] < fit["exponent_ci"][1]
    with pytest.raises(CalibrationError, match="3 or more"):
        fit_channel([5.0, 5.0, 5.0], [1e6, 1e6, 1e6], base)


def test_findings_state_whether_they_hold_with_their_numbers():
    moving = analyze(read_run(GOLDEN))
    static = copy.deepcopy(moving)
    static.name = "static"
    static.summary.update(std_throughput_per_link_mbps={"w1": 0.5}, iterations_per_min=120.0)
    lines = research_findings(moving, static)
    assert lines[0].startswith("Throughput falls with distance (golden-run): **holds**; correlation -0.8")
    assert "**holds**; per-link standard deviation 21.60 Mbit/s (golden-run) vs 0.50 Mbit/s (static)" in lines[1]
    # w2 out of range at iteration 2's start and back at 3's: a fade, not a link loss (shorter than
    # iteration_pace.SUSTAINED_OUTAGE_S), so the whole run counts
    assert lines[2].startswith("Moving computes faster than static until its link loss (research: 248 vs 192 per "
                               "minute): **does not hold**; 96.0 (golden-run, its first 2 s wall-clock) vs 120.0 "
                               "(static), per minute of computing"), lines[2]
    assert "**holds**; 1 iterations (2-2, from t=2 s wall-clock) ran without w2, cost 7.0000; all workers back " \
           "from iteration 3" in lines[3]
    moving.iterations.loc[2, "absent"] = "w2:unresponsive"  # the job's own rule for a lost worker: a link loss
    assert "**does not hold**; 120.0 (golden-run, its first 1 s wall-clock) vs 120.0" in \
        research_findings(moving, static)[2]
    static.summary["iterations_per_min"] = 119.0
    assert "**holds**; 120.0 (golden-run" in research_findings(moving, static)[2]
    moving.iterations.loc[2, "absent"] = "w2:timeout"  # a late answer, not a link loss: the whole run counts
    assert "(golden-run, its first 2 s wall-clock)" in research_findings(moving, static)[2]


def _paced_iterations(per_s: float, span_s: float, seed: int) -> pd.DataFrame:
    """Iterations begun at about per_s a simulated second (exponential gaps) over span_s, none absent."""
    starts = np.cumsum(np.random.default_rng(seed).exponential(1.0 / per_s, int(per_s * span_s * 1.5)))
    starts = starts[starts < span_s]
    return pd.DataFrame({"iteration": np.arange(len(starts)), "start_sim_s": starts, "t_s": starts, "t_rel_s": starts,
                         "duration_s": np.diff(starts, append=span_s), "absent": "", "cost": 1.0})


@pytest.mark.parametrize("moving_per_s, static_per_s, verdict", [
    (4.0, 3.0, "**holds**"), (3.0, 4.0, "**does not hold**"), (3.2, 3.0, "**not told apart**")])
def test_moving_faster_than_static_is_judged_on_the_windows_spread(moving_per_s, static_per_s, verdict):
    """Poisson paces: 60 s of moving against 200 s of static give 12 and 40 windows of 5 s, whose counts spread by
    about sqrt(20) iterations: 60 a minute apart is told apart, 12 a minute (3.2 vs 3.0 a second) is not, and the
    finding says so instead of calling the nearer figure's side."""
    moving = analyze(read_run(GOLDEN))
    static = copy.deepcopy(moving)
    moving.iterations = _paced_iterations(moving_per_s, 60.0, seed=1)
    static.iterations = _paced_iterations(static_per_s, 200.0, seed=2)
    static.summary["iterations_per_min"] = 60.0 * len(static.iterations) / 200.0
    line = research_findings(moving, static)[2]
    assert f"until its link loss (research: 248 vs 192 per minute): {verdict}; " in line, line
    assert "by 5 s windows moving minus static" in line and "(95 % interval " in line, line
    for run in (moving, static):  # a flight on the wall clock (no simulated times): its windows are wall seconds
        run.iterations["start_sim_s"] = np.nan
    assert research_findings(moving, static)[2] == line, "the same windows, from the records' wall-clock times"
    moving.iterations.loc[25, "absent"] = "w1:out_of_range"  # a fade of one iteration: not a link loss
    assert research_findings(moving, static)[2] == line
    moving.iterations.loc[25:, "absent"] = "w1:out_of_range"  # out of range to the end: lost before its fifth
    assert "too few 5 s windows for an interval" in research_findings(moving, static)[2]  # window: too few


def test_training_through_a_link_loss_is_judged_on_the_cost_over_the_same_rows():
    """While w2 is away the cost is over w1's rows; one iteration with w1 away instead (its cost over w2's rows)
    must not decide the verdict: 6.0 -> 5.0 over the three iterations without w2 holds, whatever the other's 9.0."""
    run = analyze(read_run(GOLDEN))
    its = run.iterations
    extra = its.iloc[[2, 2, 2]].copy()
    extra["iteration"], extra["cost"] = [3, 4, 5], [6.0, 5.0, 9.0]
    extra["absent"] = ["w2:out_of_range", "w2:out_of_range", "w1:timeout"]
    run.iterations = pd.concat([its.iloc[:3], extra], ignore_index=True)
    line = research_findings(run, copy.deepcopy(run))[3]
    assert "**holds**; 4 iterations (2-5" in line and "ran without w1, w2, cost 7.0000 -> 5.0000" in line, line


def test_the_runs_beside_the_research_with_ratios():
    """The golden run (4 iterations in 2.5 s, range 10 m) as both flights: each figure beside the research's,
    with NAC / research; a run shorter than 200 s is taken at its pace and says so."""
    run = analyze(read_run(GOLDEN))
    table = beside_the_research(run, copy.deepcopy(run))
    assert table[:2] == ["| figure | research | NAC | NAC / research |", "| --- | --- | --- | --- |"]
    assert "| iterations in 200 s static (golden-run), at the pace of its 2.5 s | 640 | 320 | 0.5 |" in table
    assert "| time per 10 iterations, static (s; NAC: median x 10) | 3.12 | 5 | 1.6 |" in table
    assert "| iterations in the moving flight's first 75 s (golden-run, which lasted 2.5 s) | 310 | 4 | 0.0129 |" \
        in table
    assert "| iterations after 75 s | 0 (training ended) | 0 | - |" in table
    assert "| range: throughput above 1.0 Mbit/s up to (m) | about 25 | 10 | 0.4 |" in table
    assert table[-1].startswith("The static pace is 0.5 times the testbed's, with every parameter from a source"), \
        "the gap said as a factor, and where the mechanisms are measured"
    from ground.logs.analysis import SLEEP_ON_THE_MEDIUM
    slept = copy.deepcopy(run)
    slept.problems.append(SLEEP_ON_THE_MEDIUM)  # a flight of the frame-level air on the sleep network: no gap to
    table = beside_the_research(slept, copy.deepcopy(run))  # explain by mechanisms, the air itself is missing
    assert table[-1].startswith("These runs are on the sleep network, which has none of the frame-level air's queues")
    from ground.logs.analysis import SLEEP_MODELS_THE_QUEUE
    modelled = copy.deepcopy(run)
    modelled.problems.append(SLEEP_MODELS_THE_QUEUE)  # the same with the probes' queue modelled at the master
    table = beside_the_research(modelled, copy.deepcopy(run))
    assert table[-1].startswith("These runs are on the sleep network, which models the queue the probes keep")


def test_time_per_10_beside_the_research_compares_the_nearer_and_the_farther_half_of_the_blocks():
    """With iterations of tenths of a second a far 2 m bin holds a block or two (the shipped moving flight), so the
    row splits the farthest-flown worker's blocks at their median distance: 7 near blocks and 7 far ones."""
    run = analyze(read_run(GOLDEN))
    distance_m = [6.0 + i for i in range(14)]
    run.time_per_10 = pd.DataFrame({"worker": "w2", "first_iteration": range(0, 140, 10), "t_rel_s": distance_m,
                                    "distance_m": distance_m, "time_per_10_s": [2.0] * 7 + [4.0] * 7})
    run.summary.update(time_per_10_spearman={"w2": 0.87}, max_distance_m={"w2": 19.0})
    row = [line for line in beside_the_research(run, copy.deepcopy(run)) if "against w2's distance" in line]
    assert row == ["| time per 10 iterations against w2's distance (golden-run) | rises (its Fig. 14(b)) | Spearman "
                   "rho 0.87 over the whole run (95 % interval 0.56 to 0.97; 14 blocks); median 2 s at 6-12 m (7 "
                   "blocks) and 4 s at 13-19 m (7 blocks) | - |"]


def test_time_per_10_is_judged_before_the_first_link_loss_as_the_research_flight_ended_there():
    """w2 misses iteration 100 (its link loss) and its later blocks are slow at every distance: the research's
    span is the 10 blocks before (rising, rho 0.9 from 10 blocks: 95 % interval 0.53-0.98, above 0: holds); the
    whole run's rho is said beside. A flat rho from 14 blocks (0.2: -0.37 to 0.66) does not hold."""
    run = analyze(read_run(GOLDEN))
    distance_m = [6.0 + i for i in range(10)] + [6.0, 8.0, 10.0, 12.0]
    run.time_per_10 = pd.DataFrame({"worker": "w2", "first_iteration": range(0, 140, 10), "t_rel_s": range(14),
                                    "distance_m": distance_m, "time_per_10_s": [2.0] * 5 + [4.0] * 5 + [9.0] * 4})
    run.iteration_workers = pd.DataFrame({"iteration": [99, 100], "vehicle": "w2", "present": [True, False]})
    run.summary.update(time_per_10_spearman={"w2": 0.2}, time_per_10_spearman_before_loss={"w2": 0.9},
                       time_per_10_blocks_before_loss={"w2": 10}, max_distance_m={"w2": 19.0})
    line = research_findings(run, copy.deepcopy(run))[4]
    assert line.startswith("Time per 10 iterations rises with w2's distance until its link loss (research: its Fig. "
                           "14(b)) (golden-run): **holds**; Spearman rho 0.90 before its first link loss (95 % "
                           "interval 0.53 to 0.98; 10 blocks), 0.20 over the whole run (14 blocks)."), line
    row = [line for line in beside_the_research(run, copy.deepcopy(run)) if "against w2's distance" in line]
    assert "; median 2 s at 6-10 m (5 blocks) and 4 s at 11-15 m (5 blocks) |" in row[0], "the 10 blocks before"
    run.summary["time_per_10_queue_spearman"] = {"w2": 0.8}  # the air's records say where the time went
    assert research_findings(run, copy.deepcopy(run))[4].endswith(
        "(14 blocks); with the master's queue wait in the air's records over the same blocks, rho 0.80."), "the cause"
    from ground.logs.analysis import SLEEP_MODELS_THE_QUEUE
    slept = copy.deepcopy(run)
    slept.problems.append(SLEEP_MODELS_THE_QUEUE)  # the sleep network's records hold its model of that queue
    assert research_findings(slept, copy.deepcopy(run))[4].endswith(
        "with the master's queue wait as the sleep network models it, over the same blocks, rho 0.80.")
    del run.summary["time_per_10_spearman_before_loss"]
    line = research_findings(run, copy.deepcopy(run))[4]
    assert "**does not hold**; Spearman rho 0.20 over the whole run (95 % interval -0.37 to 0.66; 14 blocks)" in line


def test_the_coded_pair_is_judged_on_its_median_iteration_with_costs_and_bytes_beside():
    """The golden run as the uncoded half, and a copy whose iterations took half the time, all complete, with half
    the bytes, as the coded half (issue 30's make coded-demo): the median, the complete share, the bytes per
    iteration and the time to the cost both reached."""
    from ground.logs.findings import coded_vs_uncoded

    uncoded = analyze(read_run(GOLDEN))
    uncoded.iterations.loc[0, "complete"] = False  # one of its 4 steps on the shards that arrived
    coded = copy.deepcopy(uncoded)
    coded.name = "coded"
    coded.iterations["duration_s"] /= 2
    coded.iterations["complete"] = True
    coded.iteration_workers["bytes_down"] //= 2  # the golden run's records have no bytes_up: 0 both ways
    lines = coded_vs_uncoded(uncoded, coded)
    assert lines[0].startswith("Coded computing finishes its iterations faster (coded vs golden-run): **holds**; "
                               "median iteration") and "50% lower" in lines[0]
    assert lines[1].startswith("Complete iterations (every row's result used): 100% of coded's vs 75% of "
                               "golden-run's")
    kb = [float(x) for x in lines[1].split("per iteration (both ways, all workers): ")[1].rstrip(".").replace(
        " kB", "").split(" vs ")]
    assert kb[1] > 0 and abs(kb[0] - kb[1] / 2) <= 0.1, kb
    assert lines[2].startswith("Time to a training cost of "), lines[2]
    assert "**does not hold**" in coded_vs_uncoded(coded, uncoded)[0]


@pytest.mark.parametrize(("speedup", "durations_sim_s", "warned"), [
    (4.0, (0.008,), True), (4.0, (0.4,), False), (1.0, (0.003,), False), (4.0, (0.008, 0.008, 0.8), False)])
def test_a_sped_up_run_of_short_iterations_is_flagged(tmp_path, speedup, durations_sim_s, warned):
    """At 4x an 8 ms iteration is 2 ms of wall-clock time: this machine's own cost per iteration; at 1x, or for
    0.4 s iterations, nothing to say. Iterations per simulated minute are 60 over the mean iteration, so the mean
    is judged: two short iterations in three (the median 8 ms) beside 0.8 s ones, a queue's tail, are 0.27 s."""
    run = tmp_path / "run"
    shutil.copytree(GOLDEN, run)
    lines = []
    iterations = 0
    for line in (run / "compute" / "compute.jsonl").read_text().splitlines():
        record = json.loads(line)
        if record["kind"] == "run_started":
            record["speedup"] = speedup
        if record["kind"] == "iteration":
            record["duration_sim_s"] = durations_sim_s[iterations % len(durations_sim_s)]
            iterations += 1
            record["workers"]["compute_s"] = [1e-5, 1e-5]
        lines.append(json.dumps(record))
    (run / "compute" / "compute.jsonl").write_text("\n".join(lines) + "\n")
    problems = " ".join(analyze(read_run(run)).problems)
    assert ("ms of wall-clock time" in problems) is warned, problems


def test_iperf3_json_beside_autopilot_logs_becomes_probes_with_distances(tmp_path):
    """A real `iperf3 --json` file run on the master against w1, and both vehicles' DataFlash logs: the probe
    takes iperf3's time and received rate, and the distance between the logged positions then; iperf3's output
    of a test that never connected is skipped by name."""
    real = SHARED_DATA / "realworld" / "iperf3"
    result = json.loads((real / "cloudpilot-baseline__baseline_target_host_direct_10.res").read_text())
    t0 = float(result["start"]["timestamp"]["timesecs"])
    run = tmp_path / "run"
    for vehicle, east_deg in (("master", 0.0), ("w1", 20.0 / 75_840.0)):  # 20 m apart at 47 N
        (run / vehicle).mkdir(parents=True)
        write_dataflash(run / vehicle / "00000001.bin",
                        [(t0 - 5 + k, 47.0, 8.0 + east_deg, 510.0) for k in range(30)], t0 - 20)
    shutil.copy(real / "cloudpilot-baseline__baseline_target_host_direct_10.res", run / "master" / "iperf3-w1.json")
    shutil.copy(real / "cloudpilot-failed__bw_host_proxy_proxy_0.res", run / "master" / "iperf3-w1.2.json")
    t = analyze(read_run(run))
    assert len(t.throughput) == 1
    probe = t.throughput.iloc[0]
    assert (probe["client"], probe["server"]) == ("master", "w1")
    assert probe["distance_m"] == pytest.approx(20.0, abs=0.1)
    assert probe["throughput_mbps"] == pytest.approx(result["end"]["sum_received"]["bits_per_second"] / 1e6)
    assert any("iperf3-w1.2.json" in p and "never connected" in p for p in t.problems), t.problems


def test_the_report_says_which_probes_ran_and_where_their_traffic_went():
    """The research measured during its training flights; a reader comparing with it must know whether the
    probes shared the job's queues, how often they ran and whether the workers were probed at once or in turn."""
    medium = {"mode": "kernel", "air": "medium"}
    line = _probes_line({"period_s": 2.0, "duration_s": 2.0, "tool": "nac", "concurrent": True}, medium)
    assert "back to back" in line and "every worker at once" in line and "same stations' queues" in line
    line = _probes_line({"period_s": 2.0, "duration_s": 0.5, "tool": "iperf3"}, {"mode": "kernel", "air": "htb"})
    assert line.startswith("iperf3, 0.5 s every 2 s (25 % of the time), one worker at a time")
    assert "rate class of their own" in line


def test_a_run_whose_scenario_had_no_probes_lacks_none_and_says_so(tmp_path):
    """A scenario without a [throughput] table runs no probes (the fleets of benchmarks/network_emulation.py): its
    report says none ran, and "what this run lacks" does not list probe records. A run whose experiment record does
    not say (or with no experiment record) still lists them as missing."""
    run = tmp_path / "run"
    shutil.copytree(GOLDEN, run)
    (run / "master" / "throughput.jsonl").unlink()
    missing = "throughput: no probe records (throughput.jsonl)"
    assert missing in analyze_run(run, draw_figures=False).missing, "no experiment record: they are missing"
    log = JsonlLog(run / "experiment.json", t_s=999.0)
    log.write(kinds.EXPERIMENT, 999.0, scenario="fleet", path="fleet.toml", speedup=1.0, speedup_note="real time",
              duration_s=10.0, network={"mode": "sleep"}, radio={"name": "wifi-flight"}, links="model",
              probes=None, vehicles=[{"id": "master", "role": "master"}, {"id": "w1", "role": "worker"}],
              missions={})
    log.close()
    t = analyze_run(run, draw_figures=False)
    report = (run / "analysis" / "report.md").read_text()
    assert missing not in t.missing and missing not in report, t.missing
    assert "- probes: none (the scenario has no [throughput] table)" in report
    assert _probes_line(None, None, recorded=False).startswith("not recorded")


def test_a_stations_queue_waits_come_from_records_that_name_their_stations():
    """The frame-level air's records name their stations from 2026-11-29 on: the master's waits are its entries,
    a station that sent nothing in a record (null) or a damaged entry is NaN, and records without names give
    nothing (older runs)."""
    from ground.logs.analysis import station_queue_waits

    records = [{"t_s": 1.0, "stations": ["master", "w1"], "queue_p50_by_station_s": [0.5, 0.004]},
               {"t_s": 2.0, "stations": ["master", "w1"], "queue_p50_by_station_s": [None, 0.004]},
               {"t_s": 3.0, "stations": ["master", "w1"], "queue_p50_by_station_s": ["x", 0.004]},
               {"t_s": 4.0, "stations": ["master"], "queue_p50_by_station_s": [0.1, 0.2]},
               {"t_s": 5.0, "queue_p50_by_station_s": [0.7, 0.004]}]
    waits = station_queue_waits(records, "master")
    assert list(waits["t_s"]) == [1.0, 2.0, 3.0] and waits["wait_s"].iloc[0] == 0.5
    assert waits["wait_s"].iloc[1:].isna().all()
    assert station_queue_waits(records, "w9").empty and station_queue_waits(records, None).empty


def test_the_airs_summary_names_what_it_could_not_carry_only_where_a_run_had_any():
    """The frame-level air's counts come from its last (cumulative) record; packets the host lost or the air could
    not carry are shown wherever any were, so a run without any keeps the summary it had."""
    from ground.logs.analysis import air_summary

    clean = {"delivered": 200, "late": 2, "queue_drops": 0, "retry_drops": 1, "collisions": 0, "exchanges": 150,
             "write_failed": 0, "unknown_destination": 0, "not_ipv4": 0, "late_p50_s": 1e-5}
    summary = air_summary([{**clean, "delivered": 100, "late": 0, "late_p50_s": 3e-5}, clean])
    assert summary["air"] == {k: clean[k] for k in ("delivered", "late", "queue_drops", "retry_drops", "collisions",
                                                    "exchanges")}
    assert summary["air_late_share"] == 0.01 and summary["air_late_median_ms"] == 0.02
    lossy = air_summary([{**clean, "write_failed": 3, "not_ipv4": 1}])["air"]
    assert (lossy["write_failed"], lossy["not_ipv4"]) == (3, 1) and "unknown_destination" not in lossy
    assert air_summary([]) == {}
    assert "air_line_cpu_pct" not in summary  # records from before the line counted its own cost
    costed = air_summary([{**clean, "packets_in": 9000, "cpu_s": 3.0, "wall_s": 60.0}])
    assert (costed["air_line_cpu_pct"], costed["air_line_packets_per_s"]) == (5.0, 150)


def test_the_reports_network_line_says_the_frame_level_air_once():
    """The runner's own words for the frame-level air are not said again beside them; a run that recorded none
    (older runs) still gets them from the report."""
    from ground.logs.report import _network_line

    why = ("namespaces on a bridge, every frame through the 802.11 medium (a FIFO queue per station, channel "
           "access, retries) at the live positions' rates")
    line = _network_line({"mode": "kernel", "air": "medium", "why": why, "congestion_control": "reno"})
    assert line.count("802.11 medium") == 1 and "probes share the queues" in line and line.endswith("TCP: reno)")
    assert "802.11 medium" in _network_line({"mode": "kernel", "air": "medium"})


def test_a_device_profiles_runs_are_warned_of_what_makes_them_depend_on_the_speed_up():
    """A device profile stretches the work, not the MPI job's own costs (this host's wall time, speed-up times that
    of simulated time at any speed-up): below 1x as above, iterations short enough on the wall clock for those to be
    over 10 % are a problem naming a speed-up low enough. Late work segments are a problem only where they add more
    than 2 % to the job's time on the rank with the most (a few, a preempted rank's, are counted, not warned of);
    a run from before the overrun was recorded is warned of by its count, as then."""
    import types

    from ground.logs.analysis import speedup_warning

    def run(speedup, late, late_s=None):
        end = {"late_cpu_segments": late, "elapsed_sim_s": 40.0}
        if late_s is not None:
            end["late_cpu_s_worst_rank"] = late_s
        return types.SimpleNamespace(compute_runs=[{"speedup": speedup, "cpu_slowdown": 1.92, "device": "jetson-tx2"}],
                                     compute_ends=[end])

    def its(mean_s):
        return pd.DataFrame({"duration_s": [mean_s] * 4})

    workers = pd.DataFrame({"iteration": [0, 1], "compute_s": [0.001, 0.001]})
    summary = {}
    warning = speedup_warning(run(0.96, 3796, 0.05), its(0.01266), workers, summary)
    assert "at 0.96x an iteration lasted 13.2 ms" in warning and "not stretched to the device's" in warning
    assert warning.endswith("run at 0.48x or lower"), warning  # (12.66 - 2.4 x 0.96) / (9 x 2.4) ms
    assert "below the simulator's slowest (0.1x)" in speedup_warning(run(0.2, 0), its(0.0025), workers, {})
    assert summary["late_cpu_segments"] == 3796 and summary["late_cpu_share"] == 0.0013
    assert speedup_warning(run(0.25, 3796, 0.05), its(0.025), workers, {}) is None  # 100 ms a wall iteration
    late = speedup_warning(run(0.25, 900, 2.0), its(0.025), workers, {})
    assert late.startswith("900 work segments took longer on this host at 0.25x") and "(5.0 % of the job's time)" \
        in late
    assert "took longer" in speedup_warning(run(0.25, 900), its(0.025), workers, {})


def test_an_analysis_without_figures_writes_the_tables_and_the_report_alone(tmp_path):
    """`nac-ground logs analyze --no-figures`: the same tables and report, no PNG and no image link in it."""
    from ground.cli import main

    assert main(["logs", "analyze", str(GOLDEN), "--out", str(tmp_path / "bare"), "--no-figures"]) == 0
    assert main(["logs", "analyze", str(GOLDEN), "--out", str(tmp_path / "drawn")]) == 0
    bare, drawn = tmp_path / "bare", tmp_path / "drawn"
    assert not list(bare.glob("*.png")) and list(drawn.glob("*.png")), "figures only where asked"
    assert sorted(p.name for p in bare.glob("*.csv")) == sorted(p.name for p in drawn.glob("*.csv"))
    assert "## Summary" in (bare / "report.md").read_text() and "![" not in (bare / "report.md").read_text()
    assert "![" in (drawn / "report.md").read_text()
