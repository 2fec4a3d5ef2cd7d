"""`nac-ground logs analyze|compare|calibrate`: a run directory in, CSV tables, PNG figures and report.md out."""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from ground.logs import figures
from ground.logs.analysis import DEFAULT_BIN_M, DEFAULT_THRESHOLD_MBPS, RunTables, analyze
from ground.logs.runlog import read_run
from nac_onboard.errors import BadInput
from nac_onboard.link.channel import ChannelModel, load_channel, save_channel

SUMMARY_LABELS = {
    "vehicles": "vehicles", "master": "master", "iterations": "iterations done",
    "complete_iterations": "complete iterations", "mean_iteration_s": "mean iteration time (s)",
    "p95_iteration_s": "p95 iteration time (s)", "iterations_per_min": "iterations per minute",
    "compute_span_s": "compute time (s)", "first_cost": "first training cost", "final_cost": "final training cost",
    "absent_iterations": "absent iterations per worker", "absence_reasons": "absence reasons",
    "probes": "throughput probes", "failed_probes": "failed probes", "mean_throughput_mbps": "mean throughput (Mbit/s)",
    "std_throughput_mbps": "throughput std, all probes (Mbit/s)",
    "std_throughput_per_link_mbps": "throughput std per link (Mbit/s)",
    "max_throughput_mbps": "max throughput (Mbit/s)",
    "range_above_threshold_m": "largest distance with throughput above threshold (m)",
    "threshold_mbps": "throughput threshold (Mbit/s)", "max_distance_m": "largest master-worker distance (m)",
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
    (out / "summary.json").write_text(json.dumps(tables.summary, indent=2, default=str) + "\n")


def _notes(tables: list[RunTables], experiment: dict | None) -> list[str]:
    lines = []
    if experiment:
        lines += ["## Experiment", "", f"- scenario: `{experiment.get('scenario')}`",
                  f"- speed-up: {experiment.get('speedup', 1)}x ({experiment.get('speedup_note', '')})",
                  f"- network: {_network_line(experiment.get('network'))}",
                  f"- ended: {experiment.get('outcome', '?')}"
                  + (f" ({experiment['detail']})" if experiment.get("outcome") not in (None, "completed") else ""),
                  ""]
    for t in tables:
        if t.missing or t.problems:
            lines += [f"## What this run lacks{f' ({t.name})' if len(tables) > 1 else ''}", ""]
            lines += [f"- {m}" for m in t.missing] + [f"- {p}" for p in t.problems] + [""]
    return lines


def _network_line(network: dict | None) -> str:
    if not network:
        return "sleep (transfers slept bits / capacity; written before the network was recorded)"
    sharing = "; the master's airtime shared" if network.get("mode") == "kernel" and network.get("sharing") else ""
    return f"{network.get('mode')} ({network.get('why', '')}{sharing})"


def analyze_run(run_dir: str | Path, out: str | Path | None = None, master: str | None = None,
                bin_m: float = DEFAULT_BIN_M, threshold_mbps: float = DEFAULT_THRESHOLD_MBPS,
                report_path: Path | None = None) -> RunTables:
    """Tables and figures into out (default RUN_DIR/analysis), report.md there or at report_path."""
    run = read_run(run_dir)
    out = Path(out) if out else run.path / "analysis"
    out.mkdir(parents=True, exist_ok=True)
    report_path = Path(report_path) if report_path else out / "report.md"
    tables = analyze(run, master, bin_m, threshold_mbps)
    write_tables(tables, out)
    pictures = {name: figures.draw(name, [tables], out / f"{name}.png") for name in figures.FIGURES}
    report = [f"# NAC run {tables.name}", "", f"Analysed from `{run.path}`; tables as CSV next to this file.", "",
              *_notes([tables], run.experiment), "## Summary", "", summary_table([tables.summary], [tables.name]), ""]
    for name, path in pictures.items():
        report += [f"![{name.replace('_', ' ')}]({_relative(path, report_path.parent)})", ""]
    report += ["## Throughput vs distance", "", markdown_table(tables.throughput_by_distance), "",
               "## Iterations", "", markdown_table(tables.iterations.drop(columns=["t_s"]), TABLE_ROWS_SHOWN), "",
               "## Master-worker distance", "", markdown_table(_every(tables.distances, 10.0), TABLE_ROWS_SHOWN), ""]
    report_path.write_text("\n".join(report))
    return tables


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
                 report_path: Path | None = None, findings=None) -> Comparison:
    """Each figure with both runs side by side, into out; report.md there or at report_path. `findings`, if given,
    turns the two runs' tables into lines for a Findings section (also returned)."""
    reads = [read_run(run_a), read_run(run_b)]
    tables = [analyze(r, master, bin_m, threshold_mbps) for r in reads]
    names = [t.name for t in tables]
    if names[0] == names[1]:
        names = [str(r.path) for r in reads]
        for t, name in zip(tables, names, strict=True):
            t.name = name
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report_path = Path(report_path) if report_path else out / "report.md"
    report = [f"# NAC runs compared: {names[0]} and {names[1]}", ""]
    lines = findings(*tables) if findings else []
    if lines:
        report += ["## Findings", "", *[f"- {line}" for line in lines], ""]
    report += [*_notes(tables, None), "## Summary", "", summary_table([t.summary for t in tables], names), ""]
    for name in figures.FIGURES:
        path = figures.draw(name, tables, out / f"{name}.png")
        report += [f"![{name.replace('_', ' ')}]({_relative(path, report_path.parent)})", ""]
    for t in tables:
        report += [f"## Throughput vs distance: {t.name}", "", markdown_table(t.throughput_by_distance), ""]
    report_path.write_text("\n".join(report))
    return Comparison(tables, lines, report_path)


# ---- calibration -------------------------------------------------------------------------------------------
class CalibrationError(BadInput):
    pass


def fit_log_distance(distance_m, throughput_bps, base: ChannelModel, saturated_fraction: float = 0.95) -> dict:
    """Log-distance path loss from throughput: each unsaturated, non-zero sample's Shannon-inverted received
    power gives a loss; PL(d) = PL(d0) + 10 n log10(d / d0) is fitted by least squares."""
    d = np.asarray(distance_m, float)
    rate = np.asarray(throughput_bps, float)
    cap = base.max_rate_bps or math.inf
    usable = np.isfinite(d) & (d > 0) & (rate > 0) & (rate < saturated_fraction * cap)
    if usable.sum() < 3 or np.ptp(np.log10(d[usable])) < 0.05:
        raise CalibrationError(f"need throughput samples below the radio's top rate at 3 or more distances "
                               f"spread over some range; found {int(usable.sum())} usable of {len(d)}")
    snr = np.power(2.0, rate[usable] / base.bandwidth_hz) - 1.0
    received_dbm = 10 * np.log10(snr * base.noise_w) + 30.0
    loss_db = base.tx_power_dbm - received_dbm
    x = 10 * np.log10(d[usable] / base.ref_distance_m)
    exponent, ref_loss_db = np.polyfit(x, loss_db, 1)
    residual = loss_db - (ref_loss_db + exponent * x)
    return {"exponent": float(exponent), "ref_loss_db": float(ref_loss_db), "samples": int(usable.sum()),
            "rms_error_db": float(np.sqrt(np.mean(residual ** 2))), "distance_min_m": float(d[usable].min()),
            "distance_max_m": float(d[usable].max())}


def calibrate_run(run_dir: str | Path, out: str | Path | None = None, base: str = "wifi-flight",
                  name: str | None = None) -> tuple[ChannelModel, dict, Path]:
    run = read_run(run_dir)
    probes = analyze(run).throughput
    if probes.empty:
        raise CalibrationError(f"{run.path}: no throughput probes to calibrate from")
    base_model = load_channel(base)
    fit = fit_log_distance(probes["distance_m"].astype(float), probes["throughput_mbps"] * 1e6, base_model)
    name = name or f"calibrated-{run.name}"
    model = ChannelModel(
        name=name, path_loss="log-distance", freq_mhz=base_model.freq_mhz, bandwidth_hz=base_model.bandwidth_hz,
        tx_power_dbm=base_model.tx_power_dbm, noise_w=base_model.noise_w, exponent=round(fit["exponent"], 4),
        ref_distance_m=base_model.ref_distance_m, ref_loss_db=round(fit["ref_loss_db"], 3),
        min_rate_bps=base_model.min_rate_bps, max_rate_bps=base_model.max_rate_bps,
        notes=f"fitted to {fit['samples']} probes of run {run.name} at {fit['distance_min_m']:.1f}-"
              f"{fit['distance_max_m']:.1f} m (rms {fit['rms_error_db']:.2f} dB); radio values from {base_model.name}")
    path = Path(out) if out else run.path / f"{name}.toml"
    save_channel(model, path)
    return model, fit, path
