"""Whether two sets of runs (the same scenario at two speed-ups) agree, judged only as far as their samples allow.

A median's confidence interval from order statistics (distribution-free: no assumption on how a loaded machine
spreads the measurements): with n samples, the k-th smallest and the k-th largest bound the median with at least the
stated confidence, k from the binomial(n, 1/2) distribution. A bin with too few samples gives no interval at all,
and is not judged. Two medians can agree within `rel` when their intervals, one widened by rel, meet.

A run's pace (iterations per simulated minute) is one number, whose spread shows only across its windows: the pace in
each window of simulated time, and two runs' ratio with an interval from those windows (ratio_interval), or two
scenarios' difference (difference_interval).

The runs' samples are pooled per distance bin: a moving flight's worker spends a few seconds in each 2 m bin, so
one run holds one or two blocks of 10 iterations there, and only several runs together say anything per bin.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats

from ground.logs import iteration_pace

#: below this, a median's 95 % interval is the whole sample's range (n = 5: k = 1) and says little: not judged
MIN_SAMPLES = 8
ALL = "all"  # every worker's samples together, as the report's throughput by distance pools the links
MIN_WINDOWS = 5  # a pace's spread from fewer windows than this is not estimated


def median_interval(values, confidence: float = 0.95) -> tuple[float, float] | None:
    """(low, high) holding the population median with at least `confidence`, or None with fewer than MIN_SAMPLES."""
    x = np.sort(np.asarray(values, dtype=float))
    n = len(x)
    if n < MIN_SAMPLES:
        return None
    tail = (1.0 - confidence) / 2
    k, below = 0, 0.0
    while True:  # the largest k with P(Binomial(n, 1/2) < k) <= tail: x[k-1] and x[n-k] bound the median
        below_next = below + math.comb(n, k) / 2 ** n
        if below_next > tail:
            break
        below, k = below_next, k + 1
    k = max(k, 1)
    return float(x[k - 1]), float(x[n - k])


def agrees_within(values, target: float, rel: float, confidence: float = 0.95) -> bool | None:
    """Whether the sample's median can be within rel of target (its interval meets the band); None: too few."""
    interval = median_interval(values, confidence)
    if interval is None:
        return None
    low, high = interval
    return low <= target * (1 + rel) and high >= target * (1 - rel)


def pace_by_window(iterations: pd.DataFrame, window_s: float) -> pd.Series:
    """Iterations begun per simulated minute in each window of window_s simulated seconds (from the run's time 0, so
    two runs' windows are the same stretch of their scenario) that lies wholly within the job's span, indexed by
    the window's start (iterations.csv: start_sim_s, duration_s)."""
    done = iterations.dropna(subset=["start_sim_s", "duration_s"])
    if done.empty:
        return pd.Series(dtype=float)
    first = math.ceil(float(done["start_sim_s"].min()) / window_s)
    last = math.floor(float((done["start_sim_s"] + done["duration_s"]).max()) / window_s)
    index = np.floor(done["start_sim_s"].to_numpy() / window_s).astype(int)
    starts = np.arange(first, last)
    counts = [(index == k).sum() for k in starts]
    return pd.Series(np.asarray(counts, dtype=float) * 60.0 / window_s, index=starts * window_s)


def ratio_interval(first: pd.Series, second: pd.Series, confidence: float = 0.95) -> tuple[float, float, float] | None:
    """The second run's pace over the first's, over the windows both hold, and the interval holding it with about
    `confidence`: the ratio estimator's standard error from the windows' residuals (second - ratio x first), so what
    both runs share window by window (where the vehicles were, what the air did) cancels and only how they differ
    counts; Student's t. None with fewer than MIN_WINDOWS windows in common or no iterations in the first."""
    common = first.index.intersection(second.index)
    a, b = first[common].to_numpy(float), second[common].to_numpy(float)
    n = len(common)
    if n < MIN_WINDOWS or a.sum() == 0:
        return None
    ratio = b.sum() / a.sum()
    se = math.sqrt(((b - ratio * a) ** 2).sum() / (n * (n - 1))) / a.mean()
    half = stats.t.ppf(0.5 + confidence / 2, n - 1) * se
    return float(ratio), float(ratio - half), float(ratio + half)


def difference_interval(first: pd.Series, second: pd.Series, confidence: float = 0.95
                        ) -> tuple[float, float, float] | None:
    """The first sample's mean minus the second's, and the interval holding it with about `confidence`: Welch's, for
    two runs' windows that share no stretch of time (two scenarios, not two speed-ups of one, for which
    ratio_interval cancels what the windows share). None with fewer than MIN_WINDOWS windows in either."""
    a, b = np.asarray(first, dtype=float), np.asarray(second, dtype=float)
    if min(len(a), len(b)) < MIN_WINDOWS:
        return None
    diff = float(a.mean() - b.mean())
    var_a, var_b = a.var(ddof=1) / len(a), b.var(ddof=1) / len(b)
    if var_a + var_b == 0:  # every window alike: the difference is known
        return diff, diff, diff
    df = (var_a + var_b) ** 2 / (var_a ** 2 / (len(a) - 1) + var_b ** 2 / (len(b) - 1))
    half = float(stats.t.ppf(0.5 + confidence / 2, df) * math.sqrt(var_a + var_b))
    return diff, diff - half, diff + half


@dataclass(frozen=True)
class BinAgreement:
    quantity: str  # "duration_s" (an iteration's, simulated), "time_per_10_s" or "throughput_mbps"
    worker: str
    distance_from_m: float | None  # None: every distance together
    samples: tuple[int, int]
    medians: tuple[float, float]
    intervals: tuple[tuple[float, float], tuple[float, float]]
    agrees: bool  # the two medians can be within rel of each other

    @property
    def ratio(self) -> float:
        return self.medians[1] / self.medians[0] if self.medians[0] else math.nan


def compare(tables: tuple[dict[str, pd.DataFrame], dict[str, pd.DataFrame]], bin_m: float = 2.0,
            rel: float = 0.10) -> list[BinAgreement]:
    """Two sets of runs, each a dict of pooled analysis tables: each iteration's simulated duration ("iterations":
    duration_s; the pace, over the whole flight), then per worker and for all together, over every distance and
    per distance bin, the time per 10 iterations ("time_per_10": worker, distance_m, time_per_10_s) and the probes'
    throughput ("throughput": server, distance_m, throughput_mbps). Only what both sets hold MIN_SAMPLES of is
    judged."""
    out = []
    if all("iterations" in t for t in tables):
        row = _judged("duration_s", ALL, None, [t["iterations"]["duration_s"].dropna() for t in tables], rel)
        out += [row] if row else []
    for quantity, table, who in (("time_per_10_s", "time_per_10", "worker"), ("throughput_mbps", "throughput",
                                                                             "server")):
        pooled = [t[table].dropna(subset=["distance_m", quantity]) for t in tables]
        for worker in [*sorted(set(pooled[0][who]) & set(pooled[1][who])), ALL]:
            mine = pooled if worker == ALL else [p[p[who] == worker] for p in pooled]
            bins = sorted(set(np.floor(mine[0]["distance_m"] / bin_m)) & set(np.floor(mine[1]["distance_m"] / bin_m)))
            for b in [None, *bins]:
                samples = [m[quantity] if b is None else m[quantity][np.floor(m["distance_m"] / bin_m) == b]
                           for m in mine]
                row = _judged(quantity, str(worker), None if b is None else float(b * bin_m), samples, rel)
                out += [row] if row else []
    return out


def _judged(quantity: str, worker: str, distance_from_m: float | None, samples, rel: float) -> BinAgreement | None:
    intervals = [median_interval(s) for s in samples]
    if None in intervals:
        return None
    (low_a, high_a), (low_b, high_b) = intervals
    return BinAgreement(quantity, worker, distance_from_m, (len(samples[0]), len(samples[1])),
                        (float(np.median(samples[0])), float(np.median(samples[1]))), (intervals[0], intervals[1]),
                        low_b <= high_a * (1 + rel) and high_b >= low_a * (1 - rel))


def pooled_rho_before_loss(run_dirs, worker: str) -> tuple[float, int] | None:
    """Spearman's rho of the worker's time per 10 iterations with its distance over every run's blocks before that
    run's first link loss of the worker (RUN/analysis/time_per_10.csv and iteration_workers.csv), and the blocks:
    runs of one scenario pooled, as one run's dozen blocks say little. None with fewer than
    iteration_pace.MIN_BLOCKS_FOR_RHO blocks."""
    tables = []
    for run in run_dirs:
        blocks = pd.read_csv(f"{run}/analysis/time_per_10.csv")
        workers = pd.read_csv(f"{run}/analysis/iteration_workers.csv")
        tables.append(iteration_pace.until_link_loss(blocks, workers))
    pooled = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=iteration_pace.BLOCK_COLUMNS)
    rho = iteration_pace.spearman(pooled[pooled["worker"] == worker])
    return (rho[worker], int((pooled["worker"] == worker).sum())) if worker in rho else None


def pooled_tables(run_dirs) -> dict[str, pd.DataFrame]:
    """The runs' analysis tables (RUN/analysis/iterations.csv, time_per_10.csv, throughput.csv) one under the
    other."""
    return {name: pd.concat([pd.read_csv(f"{run}/analysis/{name}.csv") for run in run_dirs], ignore_index=True)
            for name in ("iterations", "time_per_10", "throughput")}
