"""Time per 10 iterations against a worker's distance (ground.logs.iteration_pace), on tables made by hand."""

import numpy as np
import pandas as pd
import pytest

from ground.logs import iteration_pace


def _run(n_iterations: int, absent_w1: set[int]):
    """w1 flies from 6 m to 26 m at a steady pace, w2 hovers at 10 m; an iteration lasts 10 ms per metre of w1's
    distance while w1 takes part, 5 ms otherwise."""
    t_s = np.arange(n_iterations) * 0.5
    w1_m = 6.0 + 20.0 * t_s / t_s[-1]
    its = pd.DataFrame({"iteration": np.arange(n_iterations), "t_s": 1000.0 + t_s, "t_rel_s": t_s,
                        "duration_s": [0.005 if k in absent_w1 else 0.01 * d for k, d in enumerate(w1_m)]})
    workers = pd.DataFrame([{"iteration": k, "vehicle": v, "present": not (v == "w1" and k in absent_w1)}
                            for k in range(n_iterations) for v in ("w1", "w2")])
    dist = pd.concat([pd.DataFrame({"t_s": 1000.0 + t_s, "worker": "w1", "distance_m": w1_m}),
                      pd.DataFrame({"t_s": 1000.0 + t_s, "worker": "w2", "distance_m": 10.0})])
    return its, workers, dist


def test_blocks_keep_ten_iterations_with_the_worker_present_throughout():
    its, workers, dist = _run(205, absent_w1={33, 150, 151})
    blocks = iteration_pace.blocks(its, workers, dist)
    w1, w2 = blocks[blocks["worker"] == "w1"], blocks[blocks["worker"] == "w2"]
    assert len(w2) == 20, "the last, short block (200-204) is no block"
    assert list(w1["first_iteration"]) == [k * 10 for k in range(20) if k not in (3, 15)]
    first = w1.iloc[0]
    assert first["time_per_10_s"] == pytest.approx(its["duration_s"][:10].sum())
    assert first["distance_m"] == pytest.approx(dist[dist["worker"] == "w1"]["distance_m"][:10].mean())


def test_a_time_that_grows_with_distance_has_rho_one_and_rising_bin_medians():
    its, workers, dist = _run(400, absent_w1=set())
    blocks = iteration_pace.blocks(its, workers, dist)
    rho = iteration_pace.spearman(blocks)
    assert rho["w1"] == pytest.approx(1.0)
    assert "w2" not in rho, "one distance: no correlation to state"
    bins = iteration_pace.by_distance(blocks, 2.0)
    w1 = bins[bins["worker"] == "w1"]
    assert list(w1["distance_from_m"]) == [float(d) for d in range(6, 26, 2)]
    assert w1["median_s"].is_monotonic_increasing and w1["blocks"].sum() == 40


def test_too_few_blocks_or_no_iterations_give_nothing_to_judge():
    its, workers, dist = _run(70, absent_w1=set())
    assert iteration_pace.spearman(iteration_pace.blocks(its, workers, dist)) == {}
    empty = iteration_pace.blocks(its.iloc[:0], workers.iloc[:0], dist)
    assert empty.empty and iteration_pace.by_distance(empty, 2.0).empty


def test_blocks_before_the_first_link_loss_end_with_the_last_whole_block_before_it():
    """w1 misses iterations 57 and 150: its blocks before its first link loss are 0-49 (50-59 holds 57); w2 never
    misses one, so all its blocks are kept."""
    its, workers, dist = _run(205, absent_w1={57, 150})
    blocks = iteration_pace.blocks(its, workers, dist)
    before = iteration_pace.until_link_loss(blocks, workers)
    assert list(before[before["worker"] == "w1"]["first_iteration"]) == [0, 10, 20, 30, 40]
    assert len(before[before["worker"] == "w2"]) == len(blocks[blocks["worker"] == "w2"]) == 20
    assert iteration_pace.until_link_loss(blocks, workers.iloc[:0]).equals(blocks), "nothing known: all kept"


def test_a_late_answer_is_no_link_loss_but_every_other_absence_is():
    """w1 answers late at iteration 25 (a timeout: the iteration waited for it, and the next one waits again, so it
    took part and the block 20-29 is kept with the time waited) and is no longer waited for from 57 (unresponsive):
    its blocks before the link loss are 0-40; the blocks with 57-58 and 150 are none."""
    its, workers, dist = _run(205, absent_w1={25, 57, 58, 150})
    workers["absent"] = None
    for k, reason in ((25, "timeout"), (57, "unresponsive"), (58, "agent_lost"), (150, "timeout")):
        workers.loc[(workers["vehicle"] == "w1") & (workers["iteration"] == k), "absent"] = reason
    blocks = iteration_pace.blocks(its, workers, dist)
    before = iteration_pace.until_link_loss(blocks, workers)
    assert list(before[before["worker"] == "w1"]["first_iteration"]) == [0, 10, 20, 30, 40]
    kept = blocks[blocks["worker"] == "w1"]["first_iteration"]
    assert 20 in set(kept) and 150 in set(kept) and 50 not in set(kept)
    assert blocks[(blocks["worker"] == "w1") & (blocks["first_iteration"] == 20)]["time_per_10_s"].iloc[0] == \
        pytest.approx(its["duration_s"][20:30].sum())
    present = workers.assign(present=True, absent=None)
    assert iteration_pace.until_link_loss(blocks, present).equals(blocks), "no absence: every block"
    assert not iteration_pace.is_link_loss("timeout") and not iteration_pace.is_link_loss(" timeout")
    assert all(map(iteration_pace.is_link_loss, ("unresponsive", "agent_lost", "out_of_range", "no_position", "dead")))


def test_spearman_interval_holds_rho_and_narrows_with_blocks():
    """Fisher's z with Bonett and Wright's standard error: rho 0.34 from 24 blocks spans about -0.09 to 0.66
    (sqrt(1.058 / 21) = 0.224 in z, times 1.96); with 4 times the blocks the interval is about half as wide."""
    low, high = iteration_pace.spearman_interval(0.34, 24)
    assert low == pytest.approx(-0.087, abs=0.005) and high == pytest.approx(0.661, abs=0.005)
    low4, high4 = iteration_pace.spearman_interval(0.34, 96)
    assert low < low4 < 0.34 < high4 < high and (high4 - low4) < 0.55 * (high - low)
    assert iteration_pace.spearman_interval(1.0, 10)[1] == pytest.approx(1.0) and \
        iteration_pace.spearman_interval(0.5, 3) == (-1.0, 1.0)
    one_sided = iteration_pace.spearman_interval(0.34, 24, iteration_pace.Z_90)  # 1.645 times the same error
    assert one_sided[0] == pytest.approx(-0.015, abs=0.005) and low < one_sided[0] < 0.34 < one_sided[1] < high


def test_a_blocks_queue_wait_is_the_median_of_the_records_that_cover_it():
    """Records once a second (each the station's median wait over the second before it); iterations every 0.5 s, so
    a block spans 4.5 s and the records from its start to one second past its last iteration's start: the block
    at 0 s takes the records at 1-5 s, its wait their median. A block no record covers has none (NaN)."""
    its, workers, dist = _run(60, absent_w1=set())
    blocks = iteration_pace.blocks(its, workers, dist)
    w1 = blocks[blocks["worker"] == "w1"].reset_index(drop=True)
    waits = pd.DataFrame({"t_s": 1000.0 + np.arange(1, 21), "wait_s": np.arange(1, 21) * 0.01})  # up to 20 s
    got = iteration_pace.queue_wait_by_block(w1, its, waits)
    assert got[0] == pytest.approx(np.median(np.arange(1, 6) * 0.01))
    assert list(np.isnan(got)) == [False, False, False, False, False, True], "the last block starts at 25 s"
    assert np.all(np.diff(got[:5]) > 0), "a wait that grows gives blocks' waits that grow"
    assert iteration_pace.spearman_of(got, w1["time_per_10_s"]) is None, "5 known blocks: too few"
    assert iteration_pace.spearman_of(range(9), range(9)) == pytest.approx(1.0)
    assert np.isnan(iteration_pace.queue_wait_by_block(w1, its, waits.iloc[:1])).all(), "one record: no period"


def test_a_fade_is_no_link_loss_but_a_spell_of_the_jobs_own_rule_length_is():
    """The sleep network samples each link at an iteration's start: a spell out of range (or of the worker's agent
    unheard) shorter than SUSTAINED_OUTAGE_S (to the start of the next iteration the worker took part in) is a fade,
    which on a real network is a slow iteration; a longer one, one the run ends in, or the job's own rule for a lost
    worker (unresponsive) is a link loss, from its first iteration."""
    def track(absent: dict[int, str], t_s: list[float]) -> pd.DataFrame:
        return pd.DataFrame({"vehicle": "w1", "iteration": range(len(t_s)), "t_rel_s": t_s,
                             "present": [k not in absent for k in range(len(t_s))],
                             "absent": [absent.get(k) for k in range(len(t_s))]})

    t_s = [0.3 * k for k in range(20)] + [6.0 + 10.0 + 0.3 * k for k in range(10)]  # a 10 s gap after iteration 19
    assert iteration_pace.first_link_losses(track({3: "out_of_range", 4: "out_of_range"}, t_s)).empty, "0.6 s"
    fades_then_lost = track({3: "out_of_range", 19: "out_of_range"}, t_s)
    assert iteration_pace.first_link_losses(fades_then_lost).to_dict() == {"w1": 19}, "10.3 s out of range"
    assert iteration_pace.first_link_losses(track({5: "unresponsive"}, t_s)).to_dict() == {"w1": 5}
    assert iteration_pace.first_link_losses(track({5: "agent_lost"}, t_s)).empty, "its peer state late, once"
    assert iteration_pace.first_link_losses(track({19: "agent_lost"}, t_s)).to_dict() == {"w1": 19}
    assert iteration_pace.first_link_losses(track({28: "out_of_range", 29: "out_of_range"}, t_s)).to_dict() == \
        {"w1": 28}, "the run ended in it"
    assert iteration_pace.first_link_losses(track({3: "timeout"}, t_s)).empty, "a late answer is no absence"
