"""Time per 10 iterations against each worker's distance from the master, as the research plots it (its Fig.
14(b)): the run's iterations cut into consecutive blocks of 10, a worker's block kept while that worker took part
in all ten (in range: present, or answering after the iteration's timeout, which the iteration waited out for it as
the research's job, which had no timeout, would have waited longer), the block's time the sum of its iterations'
(simulated) durations, its distance the worker's mean distance at the ten starts. Pure: DataFrames in, DataFrames
out."""

from __future__ import annotations

import numpy as np
import pandas as pd

BLOCK_ITERATIONS = 10
MIN_BLOCKS_PER_BIN = 3  # a bin's median from fewer blocks is shown but not judged (the report says so)
MIN_BLOCKS_FOR_RHO = 8  # Spearman's rho from fewer blocks says little
Z_95 = 1.959964  # the normal distribution's two-sided 95 % quantile
Z_90 = 1.644854  # its two-sided 90 % quantile: each bound alone a one-sided 95 % bound
LATE_ANSWER = "timeout"  # an absence that is no link loss: the worker answered late and is waited for again
# Absences that say nothing of how long the link is gone (nac_onboard.compute.runner): the sleep network's one sample
# of the link model at an iteration's start (out of range, or no position then), and the worker's agent unheard by
# the master's for the peer timeout (agent_lost: its peer state, not the job's traffic, went missing; it ends when
# heard again). The job's own rule for a lost worker, unresponsive after missed deadlines, does say.
BRIEF_OUTAGE_REASONS = ("out_of_range", "no_position", "agent_lost")
# A spell of those is a link loss from this long: what the job on a real network takes to count a worker lost, 3
# missed deadlines (nac_onboard.compute.runner.UNRESPONSIVE_AFTER) of the flight scenarios' 3 s timeout. Shorter
# ones are fades a real link's TCP rides through (its retransmissions), which on the kernel network are a slow
# iteration, not an absence. Counted as losses (2026-11-29), a 0.2 s fade at 6.7 m ended paper-flight-moving's span
# at 9 s on the sleep network, where its link lasted to 30 m; and on the kernel network an agent_lost of one
# iteration at 17.5 m (w1 answering the job before and after) ended it at 36 s, where w1 was lost at 62 s.
SUSTAINED_OUTAGE_S = 9.0

BLOCK_COLUMNS = ["worker", "first_iteration", "t_rel_s", "distance_m", "time_per_10_s"]
BIN_COLUMNS = ["worker", "distance_from_m", "distance_to_m", "median_s", "p25_s", "p75_s", "blocks"]


def is_link_loss(reason) -> bool:
    """Whether a worker's absence (its reason as the job records it) is a link loss: anything but an answer that came
    after the iteration's timeout (a slow iteration; the next one waits for the worker again). Unknown: a loss."""
    return str(reason).strip() != LATE_ANSWER


def blocks(its: pd.DataFrame, workers: pd.DataFrame, dist: pd.DataFrame) -> pd.DataFrame:
    """One row per worker and block of 10 consecutive iterations in all ten of which that worker took part (present,
    or answering late)."""
    if its.empty or workers.empty or dist.empty or "present" not in workers:
        return pd.DataFrame(columns=BLOCK_COLUMNS)
    its = its.sort_values("iteration").reset_index(drop=True)
    block = np.arange(len(its)) // BLOCK_ITERATIONS
    whole = pd.Series(block).map(pd.Series(block).value_counts()) == BLOCK_ITERATIONS  # the last may be short
    rows = []
    for worker, track in dist.sort_values("t_s").groupby("worker"):
        own = workers[workers["vehicle"] == worker]
        took_part = own["present"].astype(bool)
        if "absent" in own:
            took_part |= ~own["absent"].map(is_link_loss).astype(bool)
        mine = took_part.set_axis(own["iteration"])
        mine = mine[~mine.index.duplicated(keep="last")]  # a folder holding two jobs' logs numbers iterations twice
        present = its["iteration"].map(mine).fillna(False).astype(bool)
        distance = np.interp(its["t_s"].astype(float), track["t_s"].astype(float), track["distance_m"].astype(float))
        table = pd.DataFrame({"block": block, "present": present & whole, "distance": distance,
                              "duration": its["duration_s"].astype(float), "iteration": its["iteration"],
                              "t_rel_s": its["t_rel_s"]})
        for _, b in table.groupby("block"):
            if b["present"].all():
                rows.append({"worker": worker, "first_iteration": int(b["iteration"].iloc[0]),
                             "t_rel_s": float(b["t_rel_s"].iloc[0]), "distance_m": float(b["distance"].mean()),
                             "time_per_10_s": float(b["duration"].sum())})
    return pd.DataFrame(rows, columns=BLOCK_COLUMNS)


def by_distance(table: pd.DataFrame, bin_m: float) -> pd.DataFrame:
    """Median and quartiles of the time per 10 iterations per worker and distance bin, with the blocks counted."""
    if table.empty:
        return pd.DataFrame(columns=BIN_COLUMNS)
    lower = np.floor(table["distance_m"] / bin_m) * bin_m
    grouped = table.groupby(["worker", lower])["time_per_10_s"]
    out = pd.DataFrame({"median_s": grouped.median(), "p25_s": grouped.quantile(0.25),
                        "p75_s": grouped.quantile(0.75), "blocks": grouped.count()}).reset_index()
    out = out.rename(columns={"distance_m": "distance_from_m"})
    out["distance_to_m"] = out["distance_from_m"] + bin_m
    return out[BIN_COLUMNS]


def first_link_losses(workers: pd.DataFrame) -> pd.Series:
    """Each worker's first link loss (vehicle -> the iteration it began at): a spell of consecutive absences that
    are link losses (is_link_loss) which lasts SUSTAINED_OUTAGE_S or more (from its first iteration's start to the
    start of the next one the worker took part in; a spell the run ends in counts), or holds a reason other than
    BRIEF_OUTAGE_REASONS (unresponsive: the job's own rule for a lost worker)."""
    if workers.empty or "present" not in workers:
        return pd.Series(dtype=float)
    lost = {}
    for vehicle, own in workers.sort_values("iteration").groupby("vehicle"):
        reasons = own["absent"] if "absent" in own else pd.Series(None, index=own.index)
        away = (~own["present"].astype(bool) & reasons.map(is_link_loss).astype(bool)).to_numpy()
        timed = "t_rel_s" in own  # without the iterations' times every spell counts
        t_s = own["t_rel_s"].to_numpy(float) if timed else np.zeros(len(own))
        iteration, reason = own["iteration"].to_numpy(), reasons.to_numpy()
        k = 0
        while k < len(away):
            if not away[k]:
                k += 1
                continue
            end = k
            while end < len(away) and away[end]:
                end += 1
            span_s = t_s[end] - t_s[k] if end < len(away) and timed else np.inf
            if span_s >= SUSTAINED_OUTAGE_S or any(str(r).strip() not in BRIEF_OUTAGE_REASONS for r in reason[k:end]):
                lost[vehicle] = iteration[k]
                break
            k = end
    return pd.Series(lost, dtype=float)


def until_link_loss(table: pd.DataFrame, workers: pd.DataFrame) -> pd.DataFrame:
    """Each worker's blocks before its first link loss (first_link_losses): the span the research's moving flight
    has, as its training ended at its first link loss."""
    if table.empty or workers.empty or "present" not in workers:
        return table
    first_lost = table["worker"].map(first_link_losses(workers))
    keep = first_lost.isna() | (table["first_iteration"] + BLOCK_ITERATIONS <= first_lost)
    return table[keep]


def queue_wait_by_block(table: pd.DataFrame, its: pd.DataFrame, waits: pd.DataFrame) -> np.ndarray:
    """Per block, a station's queue wait while it ran: the median of `waits` (t_s, wait_s: each the station's median
    wait over the period up to its t_s, as the delay line counts it) from the block's first iteration's start to one
    period past its last one's (the record covering it). NaN where no record fell in that span."""
    out = np.full(len(table), np.nan)
    waits = waits.dropna().sort_values("t_s")
    if table.empty or len(waits) < 2:
        return out
    period_s = float(np.median(np.diff(waits["t_s"].to_numpy(float))))
    start_s = its.set_index("iteration")["t_s"].astype(float)
    t_s, wait_s = waits["t_s"].to_numpy(float), waits["wait_s"].to_numpy(float)
    for row, first in enumerate(table["first_iteration"].astype(int)):
        if first not in start_s.index or first + BLOCK_ITERATIONS - 1 not in start_s.index:
            continue
        inside = (t_s >= start_s[first]) & (t_s <= start_s[first + BLOCK_ITERATIONS - 1] + period_s)
        if inside.any():
            out[row] = float(np.median(wait_s[inside]))
    return out


def modelled_wait_by_block(table: pd.DataFrame, waits: pd.Series) -> np.ndarray:
    """Per block, the mean of its iterations' modelled queue waits (`waits`: by iteration; the sleep network's
    master_queue_s). NaN where any of its iterations has none."""
    out = np.full(len(table), np.nan)
    for row, first in enumerate(table["first_iteration"].astype(int)):
        block = waits.reindex(range(first, first + BLOCK_ITERATIONS))
        if block.notna().all():
            out[row] = float(block.mean())
    return out


def spearman_of(x, y) -> float | None:
    """Spearman's rank correlation of two columns over the rows where both are known (None below
    MIN_BLOCKS_FOR_RHO rows or with either constant)."""
    both = pd.DataFrame({"x": np.asarray(x, float), "y": np.asarray(y, float)}).dropna()
    if len(both) < MIN_BLOCKS_FOR_RHO or both["x"].nunique() < 2 or both["y"].nunique() < 2:
        return None
    ranks = both.rank()
    return float(np.corrcoef(ranks["x"], ranks["y"])[0, 1])


def spearman_interval(rho: float, blocks: int, z: float = Z_95) -> tuple[float, float]:
    """A 95 % interval of Spearman's rho from its number of pairs (z: the normal quantile for another level):
    Fisher's z with Bonett and Wright's standard error for Spearman, sqrt((1 + rho^2 / 2) / (n - 3))
    (Psychometrika 65(1), 2000), good from about 10 pairs."""
    if blocks <= 3:
        return (-1.0, 1.0)
    half = z * np.sqrt((1.0 + rho * rho / 2.0) / (blocks - 3))
    centre = np.arctanh(np.clip(rho, -0.999999, 0.999999))
    return (float(np.tanh(centre - half)), float(np.tanh(centre + half)))


def spearman(table: pd.DataFrame) -> dict[str, float]:
    """Spearman's rank correlation of each worker's time per 10 iterations with its distance (workers with at
    least MIN_BLOCKS_FOR_RHO blocks over more than one distance)."""
    out = {}
    for worker, b in table.groupby("worker"):
        rho = spearman_of(b["distance_m"], b["time_per_10_s"])
        if rho is not None:
            out[str(worker)] = rho
    return out
