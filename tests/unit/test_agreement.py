"""ground.logs.agreement: two sets of runs compared per worker and distance bin, judged only where both hold enough."""

import numpy as np
import pandas as pd

from ground.logs.agreement import MIN_SAMPLES, MIN_WINDOWS, compare, median_interval, pace_by_window, ratio_interval


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


def test_a_runs_pace_by_window_counts_the_iterations_begun_in_each_window_the_job_spans_whole():
    starts = np.arange(0.0, 100.0, 0.5)  # 2 a second from 21 s to 120.5 s: whole windows of 30 s at 30, 60, 90
    iterations = pd.DataFrame({"start_sim_s": 21.0 + starts, "duration_s": 0.5})
    paces = pace_by_window(iterations, 30.0)
    assert paces.index.tolist() == [30.0, 60.0, 90.0] and paces.tolist() == [120.0, 120.0, 120.0]
    assert pace_by_window(iterations.iloc[:0], 30.0).empty


def test_the_ratio_interval_holds_the_true_ratio_and_tells_a_real_difference():
    """Two runs of a pace that changes over the flight (what they share window by window), each window's pace drawn
    around it with 20 % spread, the second 1.3 times the first: the interval holds 1.3 in about 95 % of draws (at
    least 90 % of 400 here), and with 5 % spread leaves out 1; with too few in common there is none."""
    rng = np.random.default_rng(4)
    shared = np.linspace(2000, 600, 12)
    index = np.arange(12) * 10.0
    held = 0
    for _ in range(400):
        a = pd.Series(shared * rng.normal(1, 0.2, 12), index=index)
        b = pd.Series(1.3 * shared * rng.normal(1, 0.2, 12), index=index)
        ratio, low, high = ratio_interval(a, b)
        held += low <= 1.3 <= high
    assert held >= 360
    steady = pd.Series(shared * rng.normal(1, 0.05, 12), index=index)
    assert ratio_interval(steady, 1.3 * steady * rng.normal(1, 0.05, 12))[1] > 1
    few = pd.Series([1.0] * (MIN_WINDOWS - 1), index=index[:MIN_WINDOWS - 1])
    assert ratio_interval(few, pd.Series(shared, index=index)) is None


def test_rho_before_the_link_loss_pools_each_runs_blocks_up_to_its_own_first_miss(tmp_path):
    """Two runs whose w1 blocks rise with distance until w1 misses an iteration (run a at 60, run b at 40) and are
    fast after it: pooled, the blocks before each loss (6 and 4) rise together (rho 1); with the later blocks the
    rise would be broken. Fewer than 8 blocks before the losses: nothing to state."""
    from ground.logs.agreement import pooled_rho_before_loss

    def run(name: str, first_miss: int) -> str:
        folder = tmp_path / name / "analysis"
        folder.mkdir(parents=True)
        n = 10
        pd.DataFrame({"worker": "w1", "first_iteration": np.arange(n) * 10, "t_rel_s": np.arange(n) * 3.0,
                      "distance_m": 6.0 + 2.0 * np.arange(n),
                      "time_per_10_s": [2.0 + 0.1 * k if 10 * k + 10 <= first_miss else 0.5 for k in range(n)]}
                     ).to_csv(folder / "time_per_10.csv", index=False)
        pd.DataFrame({"iteration": [first_miss - 1, first_miss], "vehicle": "w1", "present": [True, False]}
                     ).to_csv(folder / "iteration_workers.csv", index=False)
        return str(tmp_path / name)

    a, b = run("a", 60), run("b", 40)
    rho, blocks = pooled_rho_before_loss([a, b], "w1")
    assert blocks == 10 and rho > 0.9, (rho, blocks)
    assert pooled_rho_before_loss([a], "w1") is None, "6 blocks say little"
    assert pooled_rho_before_loss([a, b], "w2") is None
