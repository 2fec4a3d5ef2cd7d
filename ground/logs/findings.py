"""The research's findings checked against two runs' numbers (moving vs static), each line saying whether it
holds and by which figures, so a report states its evidence rather than its hopes."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ground.logs import agreement, iteration_pace
from ground.logs.analysis import SLEEP_MODELS_THE_QUEUE, SLEEP_ON_THE_MEDIUM, RunTables


def _verdict(ok: bool) -> str:
    return "**holds**" if ok else "**does not hold**"


def falls_with_distance(t: RunTables) -> str:
    probes = t.throughput.dropna(subset=["distance_m"])
    if len(probes) < 3 or probes["distance_m"].nunique() < 2:
        return f"Throughput vs distance: not enough probes in {t.name} to tell."
    rho = float(np.corrcoef(probes["distance_m"].astype(float), probes["throughput_mbps"])[0, 1])
    bins = t.throughput_by_distance
    near, far = bins.iloc[0], bins.iloc[-1]
    return (f"Throughput falls with distance ({t.name}): {_verdict(rho < 0 and far['mean_mbps'] < near['mean_mbps'])}"
            f"; correlation {rho:.2f}, {near['mean_mbps']:.1f} Mbit/s at {near['distance_from_m']:g}-"
            f"{near['distance_to_m']:g} m vs {far['mean_mbps']:.1f} Mbit/s at {far['distance_from_m']:g}-"
            f"{far['distance_to_m']:g} m.")


def pair_std_mbps(t: RunTables) -> float | None:
    """Mean over master-worker pairs of each pair's throughput standard deviation: pooling the pairs would
    count two steady links at different distances as variation."""
    stds = t.summary.get("std_throughput_per_link_mbps")
    return float(sum(stds.values()) / len(stds)) if stds else None


def variance_larger_moving(moving: RunTables, static: RunTables) -> str:
    a, b = pair_std_mbps(moving), pair_std_mbps(static)
    if a is None or b is None:
        return "Throughput variance: a run has too few probes."
    return (f"Throughput varies more moving than static: {_verdict(a > b)}; per-link standard deviation "
            f"{a:.2f} Mbit/s ({moving.name}) vs {b:.2f} Mbit/s ({static.name}), averaged over the links.")


def faster_before_link_loss(moving: RunTables, static: RunTables) -> str:
    """The research's moving flight computed faster up to its link loss than its static flight over 200 s (310
    iterations in 75 s against 640 in 200 s); here the same comparison: the moving run up to its first link loss
    (iteration_pace.first_link_losses; the whole run if none), the static run whole, per minute of
    computing. Judged on the paces of their windows of PACE_WINDOW_S (Welch's 95 % interval of the difference): a
    difference within the windows' spread is reported as not told apart, not as a verdict that would flip from run
    to run."""
    its, per_min_static = moving.iterations, static.summary.get("iterations_per_min")
    if its.empty or per_min_static is None:
        return "Iterations per minute: a run has no compute iterations."
    since = _since_start_s(moving).to_numpy()
    first_loss = _first_link_loss(its)
    lost = (its["iteration"] >= first_loss).to_numpy() if first_loss is not None else np.zeros(len(its), bool)
    upto_s = float(since[lost.argmax()]) if lost.any() else float(since[-1] + its["duration_s"].iloc[-1])
    if upto_s <= 0:
        return f"Iterations per minute: {moving.name} lost a worker at its first iteration."
    before = since < upto_s
    per_min_moving = 60.0 * int(before.sum()) / upto_s
    paper_moving, paper_static = (60.0 * PAPER_MOVING_ITERATIONS / PAPER_MOVING_LOSS_S,
                                  60.0 * PAPER_STATIC_ITERATIONS / PAPER_STATIC_S)
    clock = "simulated" if moving.clock.simulated else "wall-clock"
    told = agreement.difference_interval(_pace_by_window(since[before], its["duration_s"].to_numpy()[before]),
                                         _pace_by_window(_since_start_s(static), static.iterations["duration_s"]))
    if told is None:
        verdict, spread = _verdict(per_min_moving > per_min_static), (
            f"; too few {PACE_WINDOW_S:g} s windows for an interval, so the two figures alone decide")
    else:
        diff, low, high = told
        verdict = _verdict(True) if low > 0 else _verdict(False) if high < 0 else "**not told apart**"
        spread = (f"; by {PACE_WINDOW_S:g} s windows moving minus static {diff:+.1f} per minute (95 % interval "
                  f"{low:+.1f} to {high:+.1f})")
    return (f"Moving computes faster than static until its link loss (research: {paper_moving:.0f} vs "
            f"{paper_static:.0f} per minute): {verdict}; {per_min_moving:.1f} ({moving.name}, its first "
            f"{upto_s:.0f} s {clock}) vs {per_min_static:.1f} ({static.name}), per minute of computing{spread}.")


def _first_link_loss(its: pd.DataFrame) -> float | None:
    """The iteration any worker's first link loss began at (iteration_pace.first_link_losses), from the iterations'
    `absent` cells (VEHICLE:REASON ...)."""
    cells = [dict(a.split(":", 1) for a in str(cell).split() if ":" in a) for cell in its["absent"]]
    vehicles = sorted({v for cell in cells for v in cell})
    rows = [{"vehicle": v, "iteration": it, "t_rel_s": t, "present": v not in cell, "absent": cell.get(v)}
            for it, t, cell in zip(its["iteration"], its["t_rel_s"], cells, strict=True) for v in vehicles]
    losses = iteration_pace.first_link_losses(pd.DataFrame(rows, columns=["vehicle", "iteration", "t_rel_s",
                                                                          "present", "absent"]))
    return float(losses.min()) if not losses.empty else None


def trains_through_link_loss(moving: RunTables) -> str:
    its = moving.iterations
    partial = its[its["absent"] != ""] if not its.empty else its
    if partial.empty:
        return f"Link loss: no worker was out of range in {moving.name}, so there was nothing to train through."
    first, last = int(partial["iteration"].iloc[0]), int(partial["iteration"].iloc[-1])
    # the cost is over the rows of the workers present: compared within the commonest set of absent workers only
    # (another worker's brief absence, or the first worker's return, changes the rows it is taken over)
    away = partial["absent"].map(lambda cell: " ".join(sorted(a.split(":")[0] for a in cell.split())))
    cost = partial[away == away.value_counts().idxmax()]["cost"].dropna()
    kept_learning = len(cost) < 2 or cost.iloc[-1] < cost.iloc[0]  # one iteration: nothing to compare within
    after = its[its["iteration"] > last]
    rejoined = f"; all workers back from iteration {last + 1}" if not after.empty else ""
    absent = sorted({a.split(":")[0] for cell in partial["absent"] for a in cell.split()})
    cost_text = ("no cost logged" if cost.empty else f"cost {cost.iloc[0]:.4f}" if len(cost) == 1
                 else f"cost {cost.iloc[0]:.4f} -> {cost.iloc[-1]:.4f}")
    clock = "simulated" if moving.clock.simulated else "wall-clock"
    return (f"Training continues while a worker is out of range ({moving.name}): "
            f"{_verdict(kept_learning)}; {len(partial)} iterations "
            f"({first}-{last}, from t={partial['t_rel_s'].iloc[0]:.0f} s {clock}) ran without {', '.join(absent)}, "
            f"{cost_text}{rejoined}. The research's moving run stopped at its first link loss.")


def _farthest_flown(moving: RunTables) -> str | None:
    """The worker whose time per 10 iterations has a rho and that flew farthest from the master."""
    rho = moving.summary.get("time_per_10_spearman") or {}
    reach = moving.summary.get("max_distance_m") or {}
    return max((w for w in rho if w in reach), key=lambda w: reach[w], default=None)


def _judged_rho(moving: RunTables, worker: str) -> tuple[float, int, bool]:
    """Spearman's rho of the worker's time per 10 with its distance and its blocks: before its first link loss (the
    research's span), or over the whole run where too few blocks came before it; and whether it is the former."""
    before = moving.summary.get("time_per_10_spearman_before_loss") or {}
    if worker in before:
        return before[worker], moving.summary["time_per_10_blocks_before_loss"][worker], True
    return (moving.summary["time_per_10_spearman"][worker], int((moving.time_per_10["worker"] == worker).sum()),
            False)


def _rho_said(moving: RunTables, worker: str) -> str:
    """The judged rho with its 95 % interval and blocks, and the whole run's beside it when it differs."""
    rho, blocks, before = _judged_rho(moving, worker)
    low, high = iteration_pace.spearman_interval(rho, blocks)
    whole_blocks = int((moving.time_per_10["worker"] == worker).sum())
    if not before:
        return f"Spearman rho {rho:.2f} over the whole run (95 % interval {low:.2f} to {high:.2f}; {blocks} blocks)"
    if blocks == whole_blocks:
        return f"Spearman rho {rho:.2f} (95 % interval {low:.2f} to {high:.2f}; {blocks} blocks, no link loss)"
    whole = moving.summary["time_per_10_spearman"][worker]
    return (f"Spearman rho {rho:.2f} before its first link loss (95 % interval {low:.2f} to {high:.2f}; {blocks} "
            f"blocks), {whole:.2f} over the whole run ({whole_blocks} blocks)")


def time_rises_with_distance(moving: RunTables) -> str:
    """The research's Fig. 14(b): time per 10 iterations rises as the worker flies away, over its flight up to its
    first link loss (where its training ended). Holds when Spearman's rho of the farthest-flown worker's time per 10
    with its distance over that span is above 0 with 95 % confidence: a rise beyond the blocks' chance order."""
    worker = _farthest_flown(moving)
    if worker is None:
        return f"Time per 10 iterations vs distance: too few blocks of 10 iterations in {moving.name} to tell."
    rho, blocks, _ = _judged_rho(moving, worker)
    rises = iteration_pace.spearman_interval(rho, blocks)[0] > 0
    queue = (moving.summary.get("time_per_10_queue_spearman") or {}).get(worker)
    where = "as the sleep network models it," if SLEEP_MODELS_THE_QUEUE in moving.problems else "in the air's records"
    cause = (f"; with the master's queue wait {where} over the same blocks, rho {queue:.2f}"
             if queue is not None else "")
    return (f"Time per 10 iterations rises with {worker}'s distance until its link loss (research: its Fig. 14(b)) "
            f"({moving.name}): {_verdict(rises)}; {_rho_said(moving, worker)}{cause}.")


def _radio(*runs: RunTables) -> str:
    """Which radio model made the runs' links, with its parameters (a finding is only as good as its model)."""
    radios = {t.summary.get("radio") for t in runs}
    if radios == {None}:
        return ""
    if len(radios) == 1:
        return f" Radio: {radios.pop()}."
    return " Radios: " + "; ".join(f"{t.name}: {t.summary.get('radio') or 'not recorded'}" for t in runs) + "."


def research_findings(moving: RunTables, static: RunTables) -> list[str]:
    return [falls_with_distance(moving) + _radio(moving),
            variance_larger_moving(moving, static) + _radio(moving, static),
            faster_before_link_loss(moving, static) + _radio(moving, static),
            trains_through_link_loss(moving) + _radio(moving),
            time_rises_with_distance(moving) + _radio(moving)]


# The research's flight test (DESIGN.md section 5, from its Figs 13(a) and 14(b)): linreg, a master and 2 workers.
PAPER_STATIC_ITERATIONS = 640  # in 200 s of the static flight
PAPER_STATIC_S = 200.0
PAPER_MOVING_ITERATIONS = 310  # in the moving flight, up to its link loss
PAPER_MOVING_LOSS_S = 75.0  # the link loss that ended the research's training
# The windows a pace's spread is taken over: measured in a demo (2026-11-29), the paces of successive 5 s windows
# were near independent (lag-1 autocorrelation 0.03 static, 0.09 moving; 2.5 s: -0.34 and 0.30), and a moving
# flight's 50-55 s before its link loss hold 9-10 of them (at 10 s, 4: too few for an interval).
PACE_WINDOW_S = 5.0
PAPER_RANGE_M = 25.0  # where its throughput fell to nothing (Fig 11(b), as issue 28 reads it)


def _since_start_s(t: RunTables):
    its = t.iterations
    start = its["start_sim_s"] if its["start_sim_s"].notna().all() else its["t_s"]  # simulated, if recorded
    return start - start.iloc[0]


def _pace_by_window(since_s, duration_s):
    """Iterations' pace in each PACE_WINDOW_S from the run's first iteration (their starts as _since_start_s gives
    them: simulated time, else the wall clock's)."""
    return agreement.pace_by_window(pd.DataFrame({"start_sim_s": since_s, "duration_s": duration_s}), PACE_WINDOW_S)


def _ratio(nac: float | None, paper: float) -> str:
    return f"{nac / paper:.3g}" if nac is not None else "-"


def _time_per_10_row(moving: RunTables) -> list[tuple[str, str, str, str]]:
    """The worker that flew farthest: its blocks' time per 10 iterations before its first link loss (the research's
    span: its training ended there) in the nearer and the farther half of their distances (halves, not 2 m bins:
    when iterations take tenths of a second, a far bin holds a block or two)."""
    flown = _farthest_flown(moving)
    if flown is None:
        return []
    before = iteration_pace.until_link_loss(moving.time_per_10, moving.iteration_workers)
    mine = before[before["worker"] == flown]
    if len(mine) < 2:  # lost at once: the whole run's blocks
        mine = moving.time_per_10[moving.time_per_10["worker"] == flown]
    mine = mine.sort_values("distance_m")
    near, far = mine.iloc[:len(mine) // 2], mine.iloc[len(mine) // 2:]

    def half(b) -> str:
        return (f"{b['time_per_10_s'].median():.3g} s at {b['distance_m'].min():.0f}-{b['distance_m'].max():.0f} m "
                f"({len(b)} blocks)")

    return [(f"time per 10 iterations against {flown}'s distance ({moving.name})", "rises (its Fig. 14(b))",
             f"{_rho_said(moving, flown)}; median {half(near)} and {half(far)}", "-")]


def beside_the_research(moving: RunTables, static: RunTables) -> list[str]:
    """NAC's numbers beside the research's testbed, each with the ratio NAC / research (a markdown table). The
    research's figures are its published ones; nothing in NAC is fitted to them."""
    rows = [("figure", "research", "NAC", "NAC / research")]
    if not static.iterations.empty:
        since = _since_start_s(static)
        span_s = float(since.iloc[-1] + static.iterations["duration_s"].iloc[-1])
        within = int((since < PAPER_STATIC_S).sum())
        label = f"iterations in {PAPER_STATIC_S:g} s static ({static.name})"
        if span_s < PAPER_STATIC_S:  # a shorter run: its pace over 200 s, and said so
            within = round(len(since) * PAPER_STATIC_S / span_s)
            label += f", at the pace of its {span_s:.1f} s"
        rows.append((label, f"{PAPER_STATIC_ITERATIONS}", f"{within}", _ratio(within, PAPER_STATIC_ITERATIONS)))
        per_10_s = 10 * float(static.iterations["duration_s"].median())
        paper_10_s = 10 * PAPER_STATIC_S / PAPER_STATIC_ITERATIONS
        rows.append(("time per 10 iterations, static (s; NAC: median x 10)", f"{paper_10_s:.2f}", f"{per_10_s:.3g}",
                     _ratio(per_10_s, paper_10_s)))
    if not moving.iterations.empty:
        since = _since_start_s(moving)
        before = int((since < PAPER_MOVING_LOSS_S).sum())
        span_s = float(since.iloc[-1] + moving.iterations["duration_s"].iloc[-1])
        short = f", which lasted {span_s:.1f} s" if span_s < PAPER_MOVING_LOSS_S else ""
        rows.append((f"iterations in the moving flight's first {PAPER_MOVING_LOSS_S:g} s ({moving.name}{short})",
                     f"{PAPER_MOVING_ITERATIONS}", f"{before}", _ratio(before, PAPER_MOVING_ITERATIONS)))
        rows.append((f"iterations after {PAPER_MOVING_LOSS_S:g} s", "0 (training ended)",
                     f"{len(since) - before}", "-"))
    rows += _time_per_10_row(moving)
    reach = moving.summary.get("range_above_threshold_m")
    rows.append((f"range: throughput above {moving.summary.get('threshold_mbps', '?')} Mbit/s up to (m)",
                 f"about {PAPER_RANGE_M:g}", f"{reach:g}" if reach is not None else "-",
                 _ratio(reach, PAPER_RANGE_M)))
    lines = ["| " + " | ".join(row) + " |" for row in rows]
    if any(SLEEP_ON_THE_MEDIUM in t.problems for t in (moving, static)):  # not a gap to explain: the air is missing
        return [lines[0], "| --- | --- | --- | --- |", *lines[1:], "",
                "These runs are on the sleep network, which has none of the frame-level air's queues (the job's "
                "messages never wait behind the probes): the figures beside the research are the kernel network's "
                "(run as root), not these."]
    if any(SLEEP_MODELS_THE_QUEUE in t.problems for t in (moving, static)):  # the gaps are the model's as well
        return [lines[0], "| --- | --- | --- | --- |", *lines[1:], "",
                "These runs are on the sleep network, which models the queue the probes keep at the master by its "
                "mean and runs the probes apart from the job: the kernel network (run as root) runs the air itself, "
                "and its figures are the ones the sensitivity table explains."]
    return [lines[0], "| --- | --- | --- | --- |", *lines[1:], *_what_is_missing(rows)]


def _what_is_missing(rows: list[tuple[str, ...]]) -> list[str]:
    """The static pace's gap to the testbed said as a factor, and where the measured mechanisms are (issue 28)."""
    static = next((r for r in rows if r[0].startswith(f"iterations in {PAPER_STATIC_S:g} s static")), None)
    if static is None:
        return []
    factor = float(static[3])
    if 1 / 1.5 <= factor <= 1.5:
        return ["", f"The static pace is within a factor of 1.5 of the testbed's ({factor:.3g})."]
    return ["", f"The static pace is {factor:.3g} times the testbed's, with every parameter from a source and none "
                f"fitted to it. What each modelled mechanism adds (queues, medium access, probes in the job's "
                f"queues, a device profile) is measured by turning it off: `benchmarks/mechanisms.py`, in "
                f"docs/benchmarks.md. The factor left is what NAC does not model: Wi-Fi power saving (wake-ups at "
                f"beacon intervals of about 100 ms), the router's second hop, and Python's and MPI's cost per "
                f"message on a Jetson."]


def coded_vs_uncoded(uncoded: RunTables, coded: RunTables) -> list[str]:
    """Issue 30's pair: the same flight with the uncoded and the coded task, compared in simulated time. Judged on
    the median iteration (acceptance 3); the mean, iterations per minute, the time each took to a training cost both
    reached on complete iterations, and the bytes each iteration sent are given beside it."""
    if uncoded.iterations.empty or coded.iterations.empty:
        return ["Coded vs uncoded: a run has no compute iterations."]
    mean_a, mean_b = (float(t.iterations["duration_s"].mean()) for t in (uncoded, coded))
    median_a, median_b = (float(t.iterations["duration_s"].median()) for t in (uncoded, coded))
    share = {t.name: float(t.iterations["complete"].mean()) for t in (uncoded, coded)}
    per_iteration_kb = {t.name: _bytes_per_iteration(t) / 1e3 for t in (uncoded, coded)}
    lines = [f"Coded computing finishes its iterations faster ({coded.name} vs {uncoded.name}): "
             f"{_verdict(median_b < median_a)}; median iteration {median_b:.4g} s vs {median_a:.4g} s (simulated), "
             f"{1 - median_b / median_a:.0%} lower; mean {mean_b:.4g} s vs {mean_a:.4g} s; "
             f"{coded.summary.get('iterations_per_min', 0):.1f} vs "
             f"{uncoded.summary.get('iterations_per_min', 0):.1f} iterations per minute.",
             f"Complete iterations (every row's result used): {share[coded.name]:.0%} of {coded.name}'s vs "
             f"{share[uncoded.name]:.0%} of {uncoded.name}'s; bytes sent per iteration (both ways, all workers): "
             f"{per_iteration_kb[coded.name]:.1f} kB vs {per_iteration_kb[uncoded.name]:.1f} kB."]
    reached = _time_to_common_cost(uncoded, coded)
    if reached is not None:
        target, t_a, t_b = reached
        lines.append(f"Time to a training cost of {target:.4f} (one both runs reached: the higher of their best on "
                     f"complete iterations): {t_b:.2f} s vs {t_a:.2f} s (simulated, from each run's first "
                     f"iteration).")
    lines.append("The literature's gains are under stragglers injected on cloud machines: coded matrix "
                 "multiplication speeds up n homogeneous workers whose task times have an exponential tail by a "
                 "factor of order log n (Lee et al., IEEE Trans. Inf. Theory 2018), gradient coding recovers the "
                 "full gradient from any n - s of n workers (Tandon et al., ICML 2017), and BPCC's evaluation on "
                 "EC2 clusters (Wang et al., IEEE TNSE 2021) injects its disturbances too; here the stragglers are "
                 "physical: a worker near the edge of radio range and a slow companion.")
    return lines


def _bytes_per_iteration(t: RunTables) -> float:
    w = t.iteration_workers
    sent = [w[column].fillna(0).sum() for column in ("bytes_down", "bytes_up") if column in w]
    return float(sum(sent)) / max(len(t.iterations), 1) if sent else float("nan")


def _time_to_common_cost(a: RunTables, b: RunTables) -> tuple[float, float, float] | None:
    """(cost, a's time, b's time): the simulated time from each run's first iteration to its first complete one at
    or below the higher of the two runs' best complete-iteration cost (a cost both reached); None without costs."""
    complete = [t.iterations[t.iterations["complete"]].dropna(subset=["cost"]) for t in (a, b)]
    if any(c.empty for c in complete):
        return None
    target = max(float(c["cost"].min()) for c in complete)
    times = []
    for t, c in zip((a, b), complete, strict=True):
        clock = "start_sim_s" if t.iterations["start_sim_s"].notna().all() else "t_s"
        first = float(c[c["cost"] <= target][clock].iloc[0])
        times.append(first - float(t.iterations[clock].iloc[0]))
    return target, times[0], times[1]
