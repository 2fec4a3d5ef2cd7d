"""The tables of a run (pure: a RunLog in, pandas DataFrames out).

One time axis: unix seconds (`t_s`) as every NAC record carries it, shown as `t_rel_s` from the run's first
record on the run's own clock: simulated seconds in a SITL run at any speed-up, wall seconds otherwise
(run_clock). A telemetry position is dated by the autopilot's clock, not by when the agent happened to log it: the
agent logs the latest position at its own pace, so the time a sample was *taken* is bounded above by the earliest
log time of it or any later sample (a running minimum from the end, per boot of the autopilot). This keeps
positions of fast (or sped-up) vehicles aligned without assuming the autopilot clock's rate.

Rates and durations are in simulated seconds where the records give them (a sped-up SITL run: a probe's bits per
wall second divided by its `speedup`, an iteration's `duration_sim_s`), so a run reads the same at any speed-up.
On a kernel network each probe is set beside the rate the shaper applied to its pair at its start.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from ground.logs import energy as energy_
from ground.logs import iteration_pace
from ground.logs.run_clock import RunClock
from ground.logs.runlog import RunLog
from missions.geo import Home, ecef_to_enu, lla_to_ecef
from nac_onboard.clock import PACE_LIMIT
from nac_onboard.compute.iteration import iterations_per_min

MAX_GAP_S = 2.0  # no interpolation across a longer silence: that is a lost link, not a straight flight
DEFAULT_BIN_M = 2.0
DEFAULT_THRESHOLD_MBPS = 1.0
EVENT_COLUMNS = ["t_rel_s", "iteration", "what"]



@dataclass
class RunTables:
    name: str
    master: str | None
    t0_s: float
    clock: RunClock  # t_s to t_rel_s: simulated seconds where the run pairs them
    trajectories: pd.DataFrame  # vehicle, t_s, t_rel_s, lat/lon/alt, east_m, north_m, up_m
    distances: pd.DataFrame  # t_s, t_rel_s, worker, distance_m (master to worker)
    throughput: pd.DataFrame  # one row per probe
    throughput_by_distance: pd.DataFrame  # bins
    iterations: pd.DataFrame  # one row per compute iteration
    iteration_workers: pd.DataFrame  # one row per iteration and worker
    training_cost: pd.DataFrame
    summary: dict
    problems: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    # time per 10 iterations: blocks of 10 with a worker present throughout, and by that worker's distance
    time_per_10: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=iteration_pace.BLOCK_COLUMNS))
    time_per_10_by_distance: pd.DataFrame = field(
        default_factory=lambda: pd.DataFrame(columns=iteration_pace.BIN_COLUMNS))
    energy: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=energy_.POWER_COLUMNS))
    energy_by_vehicle: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=energy_.VEHICLE_COLUMNS))
    # faults as they happened and the MPI job's starts and stops: t_rel_s, the iteration running then, what
    events: pd.DataFrame = field(default_factory=lambda: pd.DataFrame(columns=EVENT_COLUMNS))

    def csv_tables(self) -> dict[str, pd.DataFrame]:
        return {"trajectories": self.trajectories, "distances": self.distances, "throughput": self.throughput,
                "throughput_by_distance": self.throughput_by_distance, "iterations": self.iterations,
                "iteration_workers": self.iteration_workers, "training_cost": self.training_cost,
                "time_per_10": self.time_per_10, "time_per_10_by_distance": self.time_per_10_by_distance,
                "energy": self.energy, "energy_by_vehicle": self.energy_by_vehicle, "events": self.events}


def sample_times(positions: pd.DataFrame) -> pd.Series:
    """When each position was taken, on the log's clock (see the module docstring)."""
    out = positions["t_s"].astype(float).copy()
    boot = positions["time_boot_ms"]
    if boot.isna().any():
        return out
    boot = boot.astype(float).to_numpy()
    reboot = np.concatenate([[0], np.cumsum(np.diff(boot) < 0)])
    for segment in np.unique(reboot):
        idx = np.flatnonzero(reboot == segment)
        out.iloc[idx] = np.minimum.accumulate(out.iloc[idx].to_numpy()[::-1])[::-1]
    return out


def trajectories(run: RunLog, clock: RunClock) -> pd.DataFrame:
    columns = ["vehicle", "t_s", "t_rel_s", "lat_deg", "lon_deg", "alt_m", "east_m", "north_m", "up_m"]
    if not run.positions:
        return pd.DataFrame(columns=columns)
    frames = []
    raw = pd.DataFrame(run.positions).dropna(subset=["lat_deg", "lon_deg", "alt_m"])
    for _, rows in raw.groupby("vehicle", sort=True):
        # one row per autopilot sample: the agent may log the same sample twice when none newer arrived
        rows = rows.sort_values("t_s", kind="stable")
        if rows["time_boot_ms"].notna().all():
            rows = rows.drop_duplicates(subset=["time_boot_ms", "lat_deg", "lon_deg", "alt_m"], keep="first")
        rows = rows.assign(t_s=sample_times(rows.reset_index(drop=True)).to_numpy())
        frames.append(rows)
    table = pd.concat(frames, ignore_index=True)
    ecef = lla_to_ecef(table["lat_deg"].to_numpy(), table["lon_deg"].to_numpy(), table["alt_m"].to_numpy())
    first = table.iloc[0]
    local = ecef_to_enu(ecef, Home(float(first["lat_deg"]), float(first["lon_deg"]), float(first["alt_m"])))
    table = table.assign(t_rel_s=clock.rel_s(table["t_s"].to_numpy(float)), east_m=local[:, 0], north_m=local[:, 1],
                         up_m=local[:, 2])
    return table[columns].reset_index(drop=True)


def interpolate_positions(track: pd.DataFrame, times_s: np.ndarray) -> np.ndarray:
    """ECEF positions of one vehicle at times_s, NaN outside its samples or across gaps > MAX_GAP_S."""
    t = track["t_s"].to_numpy()
    ecef = lla_to_ecef(track["lat_deg"].to_numpy(), track["lon_deg"].to_numpy(), track["alt_m"].to_numpy())
    out = np.stack([np.interp(times_s, t, ecef[:, k]) for k in range(3)], axis=-1)
    within = (times_s >= t[0]) & (times_s <= t[-1])
    after = np.searchsorted(t, times_s, side="left")  # the first sample at or after each time
    between = (after > 0) & (after < len(t))
    gap = np.zeros(len(times_s), bool)
    gap[between] = (t[after[between]] - t[after[between] - 1]) > MAX_GAP_S
    out[~within | gap] = np.nan
    return out


def distances(traj: pd.DataFrame, master: str | None, clock: RunClock) -> pd.DataFrame:
    columns = ["t_s", "t_rel_s", "worker", "distance_m"]
    if master is None or master not in set(traj["vehicle"]):
        return pd.DataFrame(columns=columns)
    m = traj[traj["vehicle"] == master]
    times = m["t_s"].to_numpy()
    master_ecef = lla_to_ecef(m["lat_deg"].to_numpy(), m["lon_deg"].to_numpy(), m["alt_m"].to_numpy())
    frames = []
    for worker in sorted(set(traj["vehicle"]) - {master}):
        w_ecef = interpolate_positions(traj[traj["vehicle"] == worker], times)
        d = np.linalg.norm(master_ecef - w_ecef, axis=1)
        frames.append(pd.DataFrame({"t_s": times, "t_rel_s": clock.rel_s(times.astype(float)), "worker": worker,
                                    "distance_m": d}))
    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=columns)
    return table.dropna(subset=["distance_m"]).reset_index(drop=True)


def _received(record: dict) -> dict:
    return (record.get("end") or {}).get("sum_received") or {}


def applied_rates(run: RunLog) -> dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]:
    """Per unordered pair: (simulated times, applied rates in bit/s) of the shaper's updates."""
    series: dict = {}
    for r in run.link_rates:
        for a, b, rate in zip(r.get("a", []), r.get("b", []), r.get("rate_bps", []), strict=False):
            series.setdefault(tuple(sorted((a, b))), []).append((r["t_sim_s"], rate))
    return {pair: (np.array([t for t, _ in v], float), np.array([x for _, x in v], float))
            for pair, v in series.items()}


def _applied_mbps(rates: dict, client, server, t_sim_s, span_sim_s) -> float | None:
    """The rate the shaper held for the pair while the probe's bytes arrived (its mean over the receiver's span;
    at its start for a failed probe): a moving pair's rate changes within one probe. None when the pair left or
    entered range during the probe: the link broke mid-probe, and no one rate describes it."""
    found = rates.get(tuple(sorted((str(client), str(server)))))
    if found is None or t_sim_s is None:
        return None
    times, values = found
    at = t_sim_s + np.linspace(0.0, span_sim_s or 0.0, 21)
    k = np.searchsorted(times, at, side="right") - 1
    held = values[k[k >= 0]]
    if held.size == 0 or ((held > 0).any() and (held == 0).any()):
        return None
    return float(held.mean()) / 1e6


def throughput(run: RunLog, clock: RunClock) -> pd.DataFrame:
    rows = []
    rates = applied_rates(run)
    for r in run.probes:
        if r.get("error_kind") == "server":
            continue  # the server refused or broke: that says nothing about the link
        got, sent = _received(r), (r.get("end") or {}).get("sum_sent") or {}
        start = (r.get("start") or {}).get("timestamp", {}).get("timesecs")
        t_s = float(start) if start is not None else r["t_s"]
        failed = "error" in r
        speedup = r.get("speedup") or 1.0
        rows.append({"t_s": t_s, "t_rel_s": clock.rel_s(t_s), "t_sim_s": r.get("t_sim_s"),
                     "client": r.get("client"), "server": r.get("server"),
                     "distance_m": r.get("distance_m"), "distance_end_m": r.get("distance_end_m"),
                     "throughput_mbps": 0.0 if failed else got.get("bits_per_second", 0.0) / speedup / 1e6,
                     "applied_mbps": _applied_mbps(rates, r.get("client"), r.get("server"), r.get("t_sim_s"),
                                                   0.0 if failed else (got.get("seconds") or 0.0) * speedup),
                     "bytes": 0 if failed else got.get("bytes", 0), "seconds": got.get("seconds"),
                     "retransmits": sent.get("retransmits"), "error": r.get("error", "")})
    columns = ["t_s", "t_rel_s", "t_sim_s", "client", "server", "distance_m", "distance_end_m", "throughput_mbps",
               "applied_mbps", "bytes", "seconds", "retransmits", "error"]
    return pd.DataFrame(rows, columns=columns).sort_values("t_s", kind="stable").reset_index(drop=True)


def with_distances(probes: pd.DataFrame, traj: pd.DataFrame) -> pd.DataFrame:
    """Probes that came without a distance (iperf3's own files beside autopilot logs) get the distance between
    their two vehicles' logged positions at the probe's start."""
    missing = probes["distance_m"].isna() & probes["client"].notna() & probes["server"].notna()
    if not missing.any() or traj.empty:
        return probes
    probes = probes.copy()
    tracks = {v: rows.sort_values("t_s") for v, rows in traj.groupby("vehicle")}
    for (client, server), rows in probes[missing].groupby(["client", "server"]):
        if client not in tracks or server not in tracks:
            continue
        times = rows["t_s"].to_numpy(float)
        a, b = interpolate_positions(tracks[client], times), interpolate_positions(tracks[server], times)
        probes.loc[rows.index, "distance_m"] = np.linalg.norm(a - b, axis=1)
    return probes


def throughput_by_distance(table: pd.DataFrame, bin_m: float = DEFAULT_BIN_M) -> pd.DataFrame:
    """Mean, standard deviation, the 95 % band (2.5 and 97.5 percentiles) and count of throughput per distance
    bin (failed probes count as 0); on a kernel network also the median rate the shaper applied and the median
    of measured / applied."""
    columns = ["distance_from_m", "distance_to_m", "mean_mbps", "std_mbps", "p2_5_mbps", "p97_5_mbps", "count"]
    applied = "applied_mbps" in table and table["applied_mbps"].notna().any()
    if applied:
        columns += ["applied_median_mbps", "measured_to_applied_median"]
    known = table.dropna(subset=["distance_m"])
    if known.empty:
        return pd.DataFrame(columns=columns)
    lower = np.floor(known["distance_m"].astype(float) / bin_m) * bin_m
    grouped = known.groupby(lower)["throughput_mbps"]
    out = pd.DataFrame({"distance_from_m": grouped.mean().index.astype(float),
                        "mean_mbps": grouped.mean().to_numpy(), "std_mbps": grouped.std(ddof=1).fillna(0.0).to_numpy(),
                        "p2_5_mbps": grouped.quantile(0.025).to_numpy(),
                        "p97_5_mbps": grouped.quantile(0.975).to_numpy(),
                        "count": grouped.count().to_numpy()})
    out["distance_to_m"] = out["distance_from_m"] + bin_m
    if applied:
        ok = known[(known["error"] == "") & (known["applied_mbps"].astype(float) > 0)].copy()  # measured ones
        ok["ratio"] = ok["throughput_mbps"] / ok["applied_mbps"].astype(float)
        by_bin = ok.groupby(lower.loc[ok.index])
        out["applied_median_mbps"] = out["distance_from_m"].map(by_bin["applied_mbps"].median())
        out["measured_to_applied_median"] = out["distance_from_m"].map(by_bin["ratio"].median())
    return out[columns]


def station_queue_waits(air_medium: list[dict], vehicle: str | None) -> pd.DataFrame:
    """The vehicle's station's median queue wait in each of the frame-level air's records (t_s, wait_s; NaN where
    it sent nothing), from records that name their stations; empty where none does."""
    rows = []
    for r in air_medium:
        stations, waits = r.get("stations"), r.get("queue_p50_by_station_s")
        if vehicle is None or not isinstance(stations, list) or vehicle not in stations or not isinstance(waits, list) \
                or len(waits) != len(stations):
            continue
        wait = waits[stations.index(vehicle)]
        ok = isinstance(wait, int | float) and not isinstance(wait, bool) and math.isfinite(wait) and wait >= 0
        rows.append({"t_s": float(r["t_s"]), "wait_s": float(wait) if ok else np.nan})
    return pd.DataFrame(rows, columns=["t_s", "wait_s"])


def iterations(run: RunLog, clock: RunClock) -> tuple[pd.DataFrame, pd.DataFrame]:
    rows, worker_rows = [], []
    for r in sorted(run.iterations, key=lambda r: r["start_s"]):
        w = r.get("workers") or {}
        ranks = w.get("rank", [])
        present = w.get("present", [])
        absent = [f"{w['vehicle'][k]}:{w['absent'][k]}" for k in range(len(ranks)) if not present[k]]
        rows.append({"iteration": r["iteration"], "t_s": r["start_s"],
                     "start_sim_s": r.get("start_sim_s", np.nan),
                     "duration_s": r.get("duration_sim_s", r["duration_s"]), "complete": bool(r.get("complete", True)),
                     "workers_present": int(sum(present)), "absent": " ".join(absent), "cost": r.get("cost")})
        for k, rank in enumerate(ranks):
            worker_rows.append({"iteration": r["iteration"], "t_s": r["start_s"], "rank": rank,
                                **{key: w[key][k] for key in w if key != "rank"}})
    it_columns = ["iteration", "t_s", "t_rel_s", "start_sim_s", "duration_s", "complete", "workers_present",
                  "absent", "cost"]
    its, workers = pd.DataFrame(rows, columns=it_columns), pd.DataFrame(worker_rows)
    its["t_rel_s"] = clock.rel_s(its["t_s"].to_numpy(float))
    if not workers.empty:
        workers.insert(1, "t_rel_s", clock.rel_s(workers.pop("t_s").to_numpy(float)))
    return its, workers


def events(run: RunLog, its: pd.DataFrame, clock: RunClock) -> pd.DataFrame:
    """Each fault and MPI job restart, at its time and the iteration running then (the cost figure's axis); none
    before the job's first iteration."""
    rows = []
    for e in run.events:
        t_rel_s = clock.rel_s(e["t_s"])
        before = its[its["t_rel_s"] <= t_rel_s] if not its.empty else its
        rows.append({"t_rel_s": t_rel_s, "iteration": int(before["iteration"].iloc[-1]) if len(before) else None,
                     "what": e["what"]})
    return pd.DataFrame(rows, columns=EVENT_COLUMNS)


def training_cost(its: pd.DataFrame) -> pd.DataFrame:
    table = its.dropna(subset=["cost"])[["iteration", "t_rel_s", "cost"]] if not its.empty else its
    if table.empty:
        return pd.DataFrame(columns=["iteration", "t_rel_s", "elapsed_s", "cost"])
    return table.assign(elapsed_s=table["t_rel_s"] - table["t_rel_s"].iloc[0])[
        ["iteration", "t_rel_s", "elapsed_s", "cost"]].reset_index(drop=True)


def range_m(bins: pd.DataFrame, threshold_mbps: float) -> float | None:
    """The far edge of the last distance bin before the first whose mean falls below the threshold."""
    reach = None
    for _, b in bins.sort_values("distance_from_m").iterrows():
        if b["mean_mbps"] < threshold_mbps:
            break
        reach = float(b["distance_to_m"])
    return reach


def summarize(run: RunLog, its: pd.DataFrame, workers: pd.DataFrame, probes: pd.DataFrame, bins: pd.DataFrame,
              dist: pd.DataFrame, threshold_mbps: float) -> dict:
    summary: dict = {"run": run.name, "vehicles": len(run.vehicles), "master": None}
    if not its.empty:
        start = its["start_sim_s"] if its["start_sim_s"].notna().all() else its["t_s"]  # simulated, if given
        first_s, last_end_s = float(start.iloc[0]), float(start.iloc[-1] + its["duration_s"].iloc[-1])
        summary.update(iterations=len(its), complete_iterations=int(its["complete"].sum()),
                       mean_iteration_s=float(its["duration_s"].mean()),
                       p95_iteration_s=float(its["duration_s"].quantile(0.95)),
                       compute_span_s=last_end_s - first_s,
                       iterations_per_min=iterations_per_min(len(its), first_s, last_end_s))
        cost = its["cost"].dropna()
        if not cost.empty:
            summary.update(first_cost=float(cost.iloc[0]), final_cost=float(cost.iloc[-1]))
    if not workers.empty and "present" in workers:
        absent = workers[~workers["present"].astype(bool)]
        summary["absent_iterations"] = {str(v): int(n) for v, n in absent.groupby("vehicle").size().items()}
        if "absent" in workers:
            summary["absence_reasons"] = sorted(set(absent["absent"].dropna().astype(str)))
    server_errors = sum(1 for r in run.probes if r.get("error_kind") == "server")
    if server_errors:
        summary["probes_not_measured"] = server_errors  # the server refused or broke: left out of the tables
    if not probes.empty:
        ok = probes[probes["error"] == ""]
        summary.update(probes=len(probes), failed_probes=int((probes["error"] != "").sum()),
                       mean_throughput_mbps=float(probes["throughput_mbps"].mean()),
                       std_throughput_mbps=float(probes["throughput_mbps"].std(ddof=1)) if len(probes) > 1 else 0.0,
                       max_throughput_mbps=float(ok["throughput_mbps"].max()) if not ok.empty else 0.0,
                       std_throughput_per_link_mbps={str(k): float(v) for k, v in probes.groupby("server")[
                           "throughput_mbps"].std(ddof=1).fillna(0.0).items()},
                       threshold_mbps=threshold_mbps, range_above_threshold_m=range_m(bins, threshold_mbps))
    if "measured_to_applied_median" in bins:
        summary["measured_to_applied_by_bin"] = {
            f"{b.distance_from_m:g}-{b.distance_to_m:g} m": round(float(b.measured_to_applied_median), 3)
            for b in bins.itertuples() if pd.notna(b.measured_to_applied_median)}
    summary.update(air_summary(run.air_medium))
    network = (run.experiment or {}).get("network")
    if network:
        summary["network"] = network.get("mode")
    radio = (run.experiment or {}).get("radio")
    if isinstance(radio, dict) and radio.get("describe"):
        summary["radio"] = str(radio["describe"])
    if not dist.empty:
        summary["max_distance_m"] = {w: float(d["distance_m"].max()) for w, d in dist.groupby("worker")}
    return summary


AIR_COUNTS = ("delivered", "late", "queue_drops", "retry_drops", "collisions", "exchanges")
AIR_NOT_CARRIED = ("write_failed", "unknown_destination", "not_ipv4")  # the host's, not the medium's: shown when any


def air_summary(records: list[dict]) -> dict:
    """The frame-level air's counts from its `air_medium` records (cumulative: the last is the run's), the share
    of deliveries written late and their typical lateness; what the delay line could not carry is named wherever a
    run had any, so no packet is lost unseen."""
    if not records:
        return {}
    air = records[-1]
    counts = {key: air.get(key) for key in AIR_COUNTS}
    counts.update({key: air[key] for key in AIR_NOT_CARRIED if air.get(key)})
    summary = {"air": counts, "air_late_share": air["late"] / air["delivered"] if air.get("delivered") else 0.0}
    late_s = [r["late_p50_s"] for r in records if r.get("late_p50_s") is not None]
    if late_s:
        summary["air_late_median_ms"] = round(float(np.median(late_s)) * 1e3, 4)
    if air.get("wall_s") and air.get("cpu_s") is not None:  # what the delay line cost this host (issue 28's target)
        summary["air_line_cpu_pct"] = round(100.0 * air["cpu_s"] / air["wall_s"], 1)
        summary["air_line_packets_per_s"] = round(air.get("packets_in", 0) / air["wall_s"])
    return summary


def analyze(run: RunLog, master: str | None = None, bin_m: float = DEFAULT_BIN_M,
            threshold_mbps: float = DEFAULT_THRESHOLD_MBPS) -> RunTables:
    starts = [min(p["t_s"] for p in run.positions)] if run.positions else []
    starts += [r["start_s"] for r in run.iterations[:1]] + [r["t_s"] for r in run.probes[:1] + run.compute_runs[:1]]
    t0_s = float(min(starts)) if starts else 0.0
    clock = RunClock.of(t0_s, run.link_rates, run.energy)
    master = run.master(master)
    traj = trajectories(run, clock)
    dist = distances(traj, master, clock)
    probes = with_distances(throughput(run, clock), traj)
    bins = throughput_by_distance(probes, bin_m)
    its, workers = iterations(run, clock)
    summary = summarize(run, its, workers, probes, bins, dist, threshold_mbps)
    summary["master"] = master
    missing = list(run.missing)
    problems = list(run.problems)
    warning = speedup_warning(run, its, workers, summary)
    if warning:
        problems.append(warning)
    network = (run.experiment or {}).get("network") or {}
    modelled = pd.Series({r["iteration"]: r["master_queue_s"] for r in run.iterations if "master_queue_s" in r},
                         dtype=float)
    if network.get("mode") == "sleep" and network.get("air") == "medium":
        problems.append(SLEEP_MODELS_THE_QUEUE if not modelled.empty else SLEEP_ON_THE_MEDIUM)
    if master is None:
        missing.append(f"master: no vehicle logged role 'master' and no probes tell (give --master ID; vehicles: "
                       f"{', '.join(sorted(run.vehicles)) or 'none'}): no distances")
    per_10 = iteration_pace.blocks(its, workers, dist)
    waits = station_queue_waits(run.air_medium, master)
    if not waits.empty:  # the frame-level air: the master's queue, where the job's messages wait behind the probes
        per_10["master_queue_s"] = iteration_pace.queue_wait_by_block(per_10, its, waits)
    elif not modelled.empty:  # the sleep network's model of that queue
        per_10["master_queue_s"] = iteration_pace.modelled_wait_by_block(per_10, modelled)
    rho = iteration_pace.spearman(per_10)
    if rho:
        summary["time_per_10_spearman"] = rho
    before_loss = iteration_pace.until_link_loss(per_10, workers)
    rho_before_loss = iteration_pace.spearman(before_loss)
    if rho_before_loss:  # the span the research's moving flight has: its training ended at its first link loss
        summary["time_per_10_spearman_before_loss"] = rho_before_loss
        summary["time_per_10_blocks_before_loss"] = {w: int((before_loss["worker"] == w).sum())
                                                     for w in rho_before_loss}
    if "master_queue_s" in before_loss:
        with_queue = {w: r for w, b in before_loss.groupby("worker")
                      if (r := iteration_pace.spearman_of(b["master_queue_s"], b["time_per_10_s"])) is not None}
        if with_queue:
            summary["time_per_10_queue_spearman"] = with_queue
    power = energy_.power(run.energy)
    vehicles = energy_.by_vehicle(power, run.battery_empty)
    summary.update(energy_.summarize(vehicles, summary))
    return RunTables(run.name, master, t0_s, clock, traj, dist, probes, bins, its, workers, training_cost(its),
                     summary, problems, missing, per_10, iteration_pace.by_distance(per_10, bin_m), power, vehicles,
                     events(run, its, clock))


SLEEP_ON_THE_MEDIUM = (
    "the scenario's air is the 802.11 medium frame by frame (a FIFO queue per station, the probes alongside the job "
    "in it), which only the kernel network has (as root): on the sleep network each message pays the medium's time on "
    "an idle medium and never waits behind the probes, which ran apart on loopback, so iterations are far shorter "
    "(paper-flight-static at 4x, 2026-11-29: 9 ms against 0.39 s on the kernel network); compare with the research "
    "from a kernel-network run")
SLEEP_MODELS_THE_QUEUE = (
    "the scenario's air is the 802.11 medium frame by frame, which only the kernel network runs (as root): on the "
    "sleep network each round of the job's inputs waited for a model of the queue the probes keep at the master (its "
    "mean, 3/4 of it for a loss-based TCP, at the links' rates), not for the queue itself; the probes ran apart on "
    "loopback (each link's throughput alone, not the two links sharing the master's air), neither channel "
    "contention nor a probe's slow start is modelled, and every round waits the queue's mean where the air's queue "
    "empties and overflows (paper-flight-static at 4x, 2026-11-29: 207 iterations a minute against 148-161 on the "
    "kernel network, 6,491 without the model; iterations of 0.26-0.33 s against 0.01-0.90 s, 10th to 90th "
    "percentile)")
MACHINE_ITERATION_COST_S = 0.0024  # a linreg iteration with 2 workers at 1x, kernel network (docs/benchmarks.md)
SHORT_ITERATION_WALL_S = 10 * MACHINE_ITERATION_COST_S
CPU_SHARE_LIMIT = 0.10
SLOWEST_SPEEDUP = 0.1  # the simulator's (sitl.experiment.scenario.MIN_SPEEDUP)
LATE_WORK_SHARE_LIMIT = 0.02  # of the job's simulated time: what the late segments may add on the rank with most


def _late_work_warning(run: RunLog, started: dict, speedup: float, summary: dict) -> str | None:
    """Work segments this host did more slowly than the device: counted in the summary, a problem when, on the rank
    with the most, they overran the device's time by more than LATE_WORK_SHARE_LIMIT of the job's simulated time (a
    rank preempted now and then runs a few segments late at any speed-up; a host too slow for the speed-up, all)."""
    end = run.compute_ends[-1] if run.compute_ends else {}
    late = int(end.get("late_cpu_segments") or 0)
    summary["device"] = f"{started.get('device')}: {started.get('cpu_slowdown'):g}x this host's CPU time"
    summary["late_cpu_segments"] = late
    if not late:
        return None
    late_s, elapsed_s = end.get("late_cpu_s_worst_rank"), end.get("elapsed_sim_s")
    if late_s is not None and elapsed_s:
        share = float(late_s) / float(elapsed_s)
        summary["late_cpu_share"] = round(share, 4)
        if share <= LATE_WORK_SHARE_LIMIT:
            return None
        by = f", by {late_s:.3g} s in all on the rank with most ({100 * share:.1f} % of the job's time)"
    else:
        by = ""  # a run from before the overrun was recorded
    return (f"{late} work segments took longer on this host at {speedup:.3g}x than on the device "
            f"({started.get('device')}){by}: their timings depend on the speed-up; run at a lower one")


def _low_enough(mean_s: float, speedup: float) -> str:
    """The speed-up at which this host's unstretched costs are 10 % of an iteration: an iteration is its modelled
    time d plus c x speed-up of this host's (c: MACHINE_ITERATION_COST_S), and c s / (d + c s) is 10 % at s = d / 9c."""
    lower = max(mean_s - MACHINE_ITERATION_COST_S * speedup, 0.0) / (9 * MACHINE_ITERATION_COST_S)
    if lower >= SLOWEST_SPEEDUP:
        return f"run at {lower:.2g}x or lower"
    return (f"under 10 % would need {lower:.2g}x, below the simulator's slowest ({SLOWEST_SPEEDUP:g}x): fewer ranks "
            "a core")


def speedup_warning(run: RunLog, its: pd.DataFrame, workers: pd.DataFrame, summary: dict) -> str | None:
    """Sped up, CPU time is X times longer in simulated seconds while transfers are not: when the workers'
    computing is more than CPU_SHARE_LIMIT of an iteration, results in simulated time depend on the speed-up. With
    a device profile the work takes the device's time on the run's clock instead, unless this host was slower."""
    started = run.compute_runs[-1] if run.compute_runs else {}
    speedup = float(started.get("speedup") or 1.0)  # the simulator's measured pace when the job started
    sped_up = speedup > PACE_LIMIT  # a 1x run's pace reads up to PACE_LIMIT while the simulator catches up
    stretched = float(started.get("cpu_slowdown") or 1.0) > 1.0
    late_warning = _late_work_warning(run, started, speedup, summary) if stretched else None
    if its.empty or workers.empty or "compute_s" not in workers or workers["compute_s"].dropna().empty:
        return late_warning
    median_s = float(its["duration_s"].median())
    mean_s = float(its["duration_s"].mean())  # iterations per simulated minute are 60 / mean_s
    # a device profile stretches the work, not the MPI job's own costs: those take this host's wall time, so
    # speed-up x that of simulated time, at any speed-up (measured: 5 vehicles, TX2 companions, iterations of
    # ~12 ms: 4,733, 5,197 and 5,525 a simulated minute at 0.96x, 0.75x and 0.5x)
    if (sped_up or (stretched and speedup < 1.0)) and 0 < mean_s / speedup < SHORT_ITERATION_WALL_S:
        return (f"at {speedup:.3g}x an iteration lasted {1e3 * mean_s / speedup:.1f} ms of wall-clock time on "
                "average: the "
                f"MPI job's own costs on this machine (about {1e3 * MACHINE_ITERATION_COST_S:.1f} ms per "
                "iteration, measured at 1x" + (", and not stretched to the device's" if stretched else "")
                + ") are more than 10 % of it, so iterations per simulated minute depend on the speed-up; "
                + (_low_enough(mean_s, speedup) if stretched else "run at 1x"))
    if late_warning:
        return late_warning
    if stretched:  # compute_s is already simulated time
        return None
    cpu_s = float(workers.groupby("iteration")["compute_s"].max().median()) * speedup
    share = cpu_s / median_s if median_s > 0 else 0.0
    summary["compute_share_of_iteration"] = round(share, 4)
    if sped_up and share > CPU_SHARE_LIMIT:
        return (f"at {speedup:g}x the workers' computing took {100 * share:.0f} % of an iteration in simulated time "
                f"(more than {100 * CPU_SHARE_LIMIT:.0f} %): iterations per simulated minute depend on the speed-up; "
                "check at a lower one")
    return None
