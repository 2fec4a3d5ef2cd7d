"""`nac-ground logs analyze|compare|calibrate`: a run directory in, CSV tables, PNG figures and report.md out."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from ground.logs import figures, iteration_pace
from ground.logs.analysis import DEFAULT_BIN_M, DEFAULT_THRESHOLD_MBPS, RunTables, analyze
from ground.logs.calibration import CalibrationError, fit_channel, fitted_model
from ground.logs.runlog import read_run
from nac_onboard.radio.channel import ChannelModel
from nac_onboard.radio.files import load_channel, save_channel
from nac_onboard.records import kinds

SUMMARY_LABELS = {
    "vehicles": "vehicles", "master": "master", "iterations": "iterations done",
    "complete_iterations": "complete iterations", "mean_iteration_s": "mean iteration time (s)",
    "p95_iteration_s": "p95 iteration time (s)", "iterations_per_min": "iterations per minute",
    "time_per_10_spearman": "time per 10 iterations vs the worker's distance: Spearman rho",
    "time_per_10_spearman_before_loss": "the same, before the worker's first link loss: Spearman rho",
    "time_per_10_blocks_before_loss": "blocks of 10 iterations before the worker's first link loss",
    "time_per_10_queue_spearman": "the same blocks' time vs the master's queue wait (frame-level air, or the sleep "
                                  "network's model of it): Spearman rho",
    "compute_span_s": "compute time (s)", "first_cost": "first training cost", "final_cost": "final training cost",
    "absent_iterations": "absent iterations per worker", "absence_reasons": "absence reasons",
    "device": "companions' CPU (device profile)", "late_cpu_segments": "work segments slower here than on it",
    "late_cpu_share": "what they added on the rank with most, of the job's time",
    "probes": "throughput probes", "failed_probes": "failed probes", "mean_throughput_mbps": "mean throughput (Mbit/s)",
    "std_throughput_mbps": "throughput std, all probes (Mbit/s)",
    "std_throughput_per_link_mbps": "throughput std per link (Mbit/s)",
    "max_throughput_mbps": "max throughput (Mbit/s)",
    "range_above_threshold_m": "largest distance with throughput above threshold (m)",
    "radio": "radio model", "threshold_mbps": "throughput threshold (Mbit/s)",
    "max_distance_m": "largest master-worker distance (m)",
    "air": "frame-level air: packets delivered, late (written over 1 ms after their time: the host fell behind), "
           "queue drops, retry drops, collisions, exchanges; where any: packets lost on this host (the receiver's air0 "
           "refused them), to no station, not IPv4",
    "air_late_share": "share of deliveries late (their timing is this host's, not the model's)",
    "air_late_median_ms": "a delivery's typical lateness, the median of each second's median (simulated ms): the "
                          "host's own work on a frame, beyond what the frame's hold left it",
    "air_line_cpu_pct": "the delay line's CPU (% of one of this host's cores, over its wall time)",
    "air_line_packets_per_s": "packets the delay line read per wall second",
    "energy_wh": "energy, every vehicle's two packs (Wh)", "companion_energy_wh": "energy, companion packs (Wh)",
    "companion_packs_empty": "companion packs that ran out",
    "energy_per_iteration_j": "energy per complete iteration, both packs (J)",
    "companion_energy_per_iteration_j": "companion energy per complete iteration (J)",
    "companion_energy_per_cost_drop_j": "companion energy per unit of training cost removed (J)",
}
TABLE_ROWS_SHOWN = 12


def _cell(value) -> str:
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k}: {_cell(v)}" for k, v in value.items()) or "none"
    if isinstance(value, list):
        return ", ".join(map(str, value)) or "none"
    return "-" if value is None else str(value)


def markdown_table(table: pd.DataFrame, max_rows: int | None = None) -> str:
    if table.empty:
        return "_(no rows)_"
    shown = table if max_rows is None or len(table) <= max_rows else table.head(max_rows)
    lines = ["| " + " | ".join(map(str, table.columns)) + " |", "|" + "---|" * len(table.columns)]
    lines += ["| " + " | ".join(_cell(v) for v in row) + " |" for row in shown.itertuples(index=False)]
    if len(shown) < len(table):
        lines.append(f"\n_first {len(shown)} of {len(table)} rows; all in the CSV_")
    return "\n".join(lines)


def summary_table(summaries: list[dict], names: list[str]) -> str:
    keys = [k for k in SUMMARY_LABELS if any(k in s for s in summaries)]
    rows = [[SUMMARY_LABELS[k], *(_cell(s.get(k)) for s in summaries)] for k in keys]
    return markdown_table(pd.DataFrame(rows, columns=["", *names]))


def write_tables(tables: RunTables, out: Path) -> None:
    for name, table in tables.csv_tables().items():
        table.to_csv(out / f"{name}.csv", index=False)
    (out / kinds.SUMMARY.name).write_text(json.dumps(tables.summary, indent=2, default=str) + "\n")


def _notes(tables: list[RunTables], experiment: dict | None) -> list[str]:
    lines = []
    if experiment:
        probes = _probes_line(experiment.get("probes"), experiment.get("network"), "probes" in experiment)
        lines += ["## Experiment", "", f"- scenario: `{experiment.get('scenario')}`",
                  f"- speed-up: {float(experiment.get('speedup') or 1):g}x ({experiment.get('speedup_note', '')})",
                  f"- network: {_network_line(experiment.get('network'))}",
                  f"- probes: {probes}",
                  f"- ended: {experiment.get('outcome', '?')}"
                  + (f" ({experiment['detail']})" if experiment.get("outcome") not in (None, "completed") else ""),
                  ""]
    for t in tables:
        if t.missing or t.problems:
            lines += [f"## What this run lacks{f' ({t.name})' if len(tables) > 1 else ''}", ""]
            lines += [f"- {m}" for m in t.missing] + [f"- {p}" for p in t.problems] + [""]
    return lines


def _probes_line(probes: dict | None, network: dict | None, recorded: bool = True) -> str:
    """Which probes ran and where their traffic went: beside the job in its queues, or apart from it. recorded:
    whether the experiment's record says (runs from before it did have no `probes` at all)."""
    if not recorded:
        return "not recorded (a run from before the experiment recorded its probes)"
    if not probes:
        return "none (the scenario has no [throughput] table)"
    period_s, duration_s = probes.get("period_s", 0), probes.get("duration_s", 0)
    schedule = "back to back (continuous, as iperf3's tests)" if duration_s >= period_s else \
        f"{duration_s:g} s every {period_s:g} s ({100 * duration_s / period_s:.0f} % of the time)"
    schedule += ", every worker at once (a client per link)" if probes.get("concurrent") else ", one worker at a time"
    tool = "iperf3" if probes.get("tool") == "iperf3" else "nac-onboard's probe"
    network = network or {}
    if network.get("mode") != "kernel":
        where = "over this host's loopback, apart from the job's slept transfers"
    elif network.get("air") == "medium":
        where = "alongside the job, in the same stations' queues"
    else:
        where = "in a rate class of their own, apart from the job's traffic"
    return f"{tool}, {schedule}, {where}"


def _network_line(network: dict | None) -> str:
    if not network:
        return "sleep (transfers slept bits / capacity; written before the network was recorded)"
    kernel = network.get("mode") == "kernel"
    if kernel and network.get("air") == "medium":  # the runner's why names the medium already: said once
        air = ("; probes share the queues" if "802.11 medium" in network.get("why", "") else
               "; the air frame by frame (802.11 medium: one FIFO queue per station, channel access, retries; "
               "probes share the queues)")
    else:
        air = "; the master's airtime shared" if kernel and network.get("sharing") else ""
    tcp = network.get("congestion_control")
    if kernel and tcp:
        air += "; the companions' TCP: " + ("this host's default" if tcp == "host" else tcp)
    return f"{network.get('mode')} ({network.get('why', '')}{air})"


def analyze_run(run_dir: str | Path, out: str | Path | None = None, master: str | None = None,
                bin_m: float = DEFAULT_BIN_M, threshold_mbps: float = DEFAULT_THRESHOLD_MBPS,
                report_path: Path | None = None, draw_figures: bool = True) -> RunTables:
    """Tables and figures into out (default RUN_DIR/analysis), report.md there or at report_path. draw_figures:
    False for the tables and the report alone (the figures are most of an analysis's time: 1.2 s of a short run's
    2.8, 2026-11-29)."""
    run = read_run(run_dir)
    out = Path(out) if out else run.path / kinds.ANALYSIS_DIR
    out.mkdir(parents=True, exist_ok=True)
    report_path = Path(report_path) if report_path else out / kinds.REPORT.name
    tables = analyze(run, master, bin_m, threshold_mbps)
    write_tables(tables, out)
    pictures = {name: figures.draw(name, [tables], out / f"{name}.png") for name in figures.FIGURES
                if draw_figures and figures.ONLY_WITH_DATA.get(name, bool)(tables)}
    report = [f"# {tables.name}: a NAC run", "", f"Analysed from `{run.path}`; tables as CSV next to this file.", "",
              *_notes([tables], run.experiment), "## Summary", "", summary_table([tables.summary], [tables.name]), ""]
    for name, path in pictures.items():
        report += [f"![{name.replace('_', ' ')}]({_relative(path, report_path.parent)})", ""]
    report += ["## Throughput vs distance", "", markdown_table(tables.throughput_by_distance), "",
               *_time_per_10_section(tables), *_energy_section(tables, run.energy_plan),
               "## Iterations", "", markdown_table(tables.iterations.drop(columns=["t_s"]), TABLE_ROWS_SHOWN), "",
               "## Master-worker distance", "", markdown_table(_every(tables.distances, 10.0), TABLE_ROWS_SHOWN), ""]
    report_path.write_text("\n".join(report))
    return tables


def _time_per_10_section(t: RunTables) -> list[str]:
    """The research's Fig. 14(b) as a table: time per 10 iterations by each worker's distance, with Spearman's rho."""
    if t.time_per_10_by_distance.empty:
        return []
    rho = t.summary.get("time_per_10_spearman", {})
    before = t.summary.get("time_per_10_spearman_before_loss", {})
    blocks_before = t.summary.get("time_per_10_blocks_before_loss", {})

    def one(w: str, r: float) -> str:
        blocks = int((t.time_per_10["worker"] == w).sum())
        low, high = iteration_pace.spearman_interval(r, blocks)
        text = f"{w}: {r:.2f} over {blocks} blocks (95 % interval {low:.2f} to {high:.2f})"
        if w in before and blocks_before[w] < blocks:
            low, high = iteration_pace.spearman_interval(before[w], blocks_before[w])
            text += (f", {before[w]:.2f} over the {blocks_before[w]} before its first link loss ({low:.2f} to "
                     f"{high:.2f})")
        return text

    said = "; ".join(one(w, r) for w, r in rho.items())
    queue = t.summary.get("time_per_10_queue_spearman", {})
    if queue:
        said += (". The blocks' time against the master's queue wait while they ran (the frame-level air's records), "
                 "before each worker's first link loss: " + "; ".join(f"{w}: {r:.2f}" for w, r in queue.items()))
    return ["## Time per 10 iterations vs distance", "",
            "Blocks of 10 consecutive iterations in all ten of which the worker took part (present, or answering "
            "after the iteration's timeout) (simulated seconds), by that "
            f"worker's mean distance from the master; bins of fewer than {iteration_pace.MIN_BLOCKS_PER_BIN} blocks "
            f"say little. Spearman's rank correlation of time with distance: {said or 'too few blocks'}.", "",
            markdown_table(t.time_per_10_by_distance), ""]


def _energy_section(t: RunTables, plan: dict | None) -> list[str]:
    """Each vehicle's energy by what used it: the integral of the power it recorded each simulated second."""
    if t.energy_by_vehicle.empty:
        return []
    plan = plan or {}
    companion, radio = plan.get("companion") or {}, plan.get("radio") or {}
    frames = ", ".join(f"{v}: {f}" for v, f in (plan.get("frames") or {}).items())
    radio_said = "from its station's bytes" if plan.get("radio_counted") else "idle only (no station counters here)"
    return ["## Energy", "",
            f"Flight power from the frame's propulsion model ({frames}); the companion's "
            f"{companion.get('name', '?')} ({companion.get('idle_w', '?')} W idle, {companion.get('busy_w', '?')} W "
            f"busy) from its rank's CPU time, and its radio {radio.get('name', '?')} {radio_said}, through converters "
            f"of efficiency {plan.get('dc_dc_efficiency', '?')}; sources in sitl/vehicle/energy.py. Wh over the "
            "scenario; state of charge at its end.", "", markdown_table(t.energy_by_vehicle), ""]


def _every(table: pd.DataFrame, step_s: float) -> pd.DataFrame:
    """One row per worker every step_s, for a readable excerpt."""
    if table.empty:
        return table
    slot = (table["t_rel_s"] // step_s).astype(int)
    return table.assign(slot=slot).drop_duplicates(["worker", "slot"]).drop(columns=["slot", "t_s"])


def _relative(path: Path, base: Path) -> str:
    return os.path.relpath(path, base)


@dataclass(frozen=True)
class Comparison:
    tables: list[RunTables]
    findings: list[str]
    report_path: Path


def compare_runs(run_a: str | Path, run_b: str | Path, out: str | Path, master: str | None = None,
                 bin_m: float = DEFAULT_BIN_M, threshold_mbps: float = DEFAULT_THRESHOLD_MBPS,
                 report_path: Path | None = None, findings=None, beside=None) -> Comparison:
    """Each figure with both runs side by side, into out; report.md there or at report_path. `findings`, if given,
    turns the two runs' tables into lines for a Findings section (also returned); `beside`, into a markdown table
    of the runs beside the research."""
    reads = [read_run(run_a), read_run(run_b)]
    tables = [analyze(r, master, bin_m, threshold_mbps) for r in reads]
    names = [t.name for t in tables]
    if names[0] == names[1]:
        names = [str(r.path) for r in reads]
        for t, name in zip(tables, names, strict=True):
            t.name = name
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report_path = Path(report_path) if report_path else out / kinds.REPORT.name
    report = [f"# NAC runs compared: {names[0]} and {names[1]}", ""]
    lines = findings(*tables) if findings else []
    if lines:
        report += ["## Findings", "", *[f"- {line}" for line in lines], ""]
    if beside:
        report += ["## Beside the research", "", *beside(*tables), ""]
    report += [*_notes(tables, None), "## Summary", "", summary_table([t.summary for t in tables], names), ""]
    for name in [n for n in figures.FIGURES if any(figures.ONLY_WITH_DATA.get(n, bool)(t) for t in tables)]:
        path = figures.draw(name, tables, out / f"{name}.png")
        report += [f"![{name.replace('_', ' ')}]({_relative(path, report_path.parent)})", ""]
    path = figures.draw_iteration_time_distribution(tables, out / "iteration_time_distribution.png")
    report += [f"![iteration time distribution]({_relative(path, report_path.parent)})", ""]
    for t in tables:
        report += [f"## Throughput vs distance: {t.name}", "", markdown_table(t.throughput_by_distance), ""]
    report_path.write_text("\n".join(report))
    return Comparison(tables, lines, report_path)


# ---- calibration -------------------------------------------------------------------------------------------
def calibrate_run(run_dir: str | Path, out: str | Path | None = None, base: str = "wifi-flight",
                  name: str | None = None, samples_per_probe: int = 10) -> tuple[ChannelModel, dict, Path]:
    """Fit the base radio's path loss and shadowing to a run's probes; write the preset (TOML) and a figure of
    measured against fitted throughput by distance beside it."""
    run = read_run(run_dir)
    probes = analyze(run).throughput.dropna(subset=["distance_m"])
    if probes.empty:
        raise CalibrationError(f"{run.path}: no throughput probes with a distance to calibrate from")
    base_model = load_channel(base)
    fit = fit_channel(probes["distance_m"].astype(float), probes["throughput_mbps"] * 1e6, base_model,
                      samples_per_probe)
    name = name or f"calibrated-{run.name}"
    model = fitted_model(base_model, fit, name, f"run {run.name}")
    path = Path(out) if out else run.path / f"{name}.toml"
    save_channel(model, path)
    fit["figure"] = str(figures.draw_calibration(probes, model, path.with_suffix(".png")))
    return model, fit, path
