"""ground.logs.agreement: two sets of runs compared per worker and distance bin, judged only where both hold enough."""

import numpy as np
import pandas as pd

from ground.logs.agreement import MIN_SAMPLES, compare, median_interval


def tables(rng, scale: float = 1.0, far_blocks: int = 20) -> dict[str, pd.DataFrame]:
    """w1's blocks at 6-8 m (30) and 20-22 m (far_blocks, slower), w2's at 10-12 m; probes likewise."""
    near = pd.DataFrame({"worker": "w1", "distance_m": rng.uniform(6, 8, 30),
                         "time_per_10_s": scale * rng.lognormal(np.log(2.0), 0.3, 30)})
    far = pd.DataFrame({"worker": "w1", "distance_m": rng.uniform(20, 22, far_blocks),
                        "time_per_10_s": scale * rng.lognormal(np.log(4.0), 0.3, far_blocks)})
    w2 = pd.DataFrame({"worker": "w2", "distance_m": rng.uniform(10, 12, 40),
                       "time_per_10_s": scale * rng.lognormal(np.log(3.0), 0.3, 40)})
    per_10 = pd.concat([near, far, w2], ignore_index=True)
    probes = per_10.rename(columns={"worker": "server"}).assign(throughput_mbps=lambda t: 30.0 / t["time_per_10_s"])
    iterations = pd.DataFrame({"duration_s": scale * rng.lognormal(np.log(0.3), 0.5, 300)})
    return {"iterations": iterations, "time_per_10": per_10, "throughput": probes.drop(columns="time_per_10_s")}


def test_the_same_process_at_both_speedups_agrees_in_every_judged_bin():
    rng = np.random.default_rng(1)
    rows = compare((tables(rng), tables(rng)))
    judged = {(r.quantity, r.worker, r.distance_from_m) for r in rows}
    assert ("time_per_10_s", "w1", None) in judged and ("time_per_10_s", "w1", 20.0) in judged
    assert ("throughput_mbps", "w2", 10.0) in judged and ("duration_s", "all", None) in judged
    assert all(r.agrees for r in rows), rows


def test_a_pace_twice_as_slow_is_told_apart_in_every_bin():
    """The pace, and each bin; a worker's whole flight mixes its near and far blocks."""
    rng = np.random.default_rng(2)
    rows = [r for r in compare((tables(rng), tables(rng, scale=2.0)))
            if r.distance_from_m is not None or r.quantity == "duration_s"]
    assert len(rows) == 13 and not any(r.agrees for r in rows), rows
    expected = {"duration_s": 2.0, "time_per_10_s": 2.0, "throughput_mbps": 0.5}
    assert all(abs(r.ratio / expected[r.quantity] - 1) < 0.3 for r in rows), rows


def test_a_bin_with_too_few_samples_at_either_speedup_is_not_judged():
    rng = np.random.default_rng(3)
    rows = compare((tables(rng), tables(rng, far_blocks=MIN_SAMPLES - 1)))
    assert not [r for r in rows if r.distance_from_m == 20.0], rows
    assert [r for r in rows if r.worker == "w1" and r.distance_from_m is None], "the whole flight still is"


def test_the_median_interval_holds_the_median_and_needs_enough_samples():
    assert median_interval(range(MIN_SAMPLES - 1)) is None
    low, high = median_interval(range(101))
    assert low < 50 < high and high - low < 30
