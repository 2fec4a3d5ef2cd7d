"""The straggler codes (nac_onboard.compute.codes) and the coded tasks on them, in one process: every subset the
code promises decodes, and the tasks' results equal the uncoded ones."""

import itertools
from types import SimpleNamespace

import numpy as np
import pytest

from nac_onboard.compute import codes, kernels
from nac_onboard.compute.task import Answer
from nac_onboard.compute.tasks.linreg import Linreg
from nac_onboard.compute.tasks.linreg_gc import GradientCodedLinreg
from nac_onboard.compute.tasks.matmul_bpcc import BpccMatmul
from nac_onboard.compute.tasks.matmul_mds import MdsMatmul
from nac_onboard.errors import BadInput
from tests.conftest import SHARED_DATA


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6])
def test_any_k_of_n_coded_products_decode_a_times_b(n):
    rng = np.random.default_rng(n)
    for k in range(1, n + 1):
        generator = codes.mds_generator(n, k)
        blocks, b = rng.standard_normal((k, 5, 30)), rng.standard_normal((30, 2))
        products = np.stack([block @ b for block in blocks])
        coded = codes.encode(generator, blocks)
        assert codes.worst_condition(generator) < 100, "three vehicles to seven: two digits lost at most"
        for used in itertools.permutations(range(n), k) if n <= 4 else itertools.combinations(range(n), k):
            decoded, _ = codes.mds_decode(generator, list(used), np.stack([coded[u] @ b for u in used]))
            assert np.linalg.norm(decoded - products) <= 1e-9 * np.linalg.norm(products), (n, k, used)


def test_impossible_codes_and_ill_conditioned_decodes_are_refused():
    with pytest.raises(codes.CodeError, match="1 <= k <= n"):
        codes.mds_generator(3, 4)
    with pytest.raises(codes.CodeError, match="0 <= s < n"):
        codes.gradient_code(3, 3)
    nearly_equal = np.array([[1.0, 0.0], [1.0, 1.0], [1.0, 1.0 + 1e-12]])
    with pytest.raises(codes.CodeError, match="condition number"):
        codes.mds_decode(nearly_equal, [1, 2], np.ones((2, 3)))


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6])
def test_any_n_minus_s_coded_gradients_give_the_full_gradient(n):
    rng = np.random.default_rng(n)
    gradients = rng.standard_normal((n, 13))  # one per shard
    for s in range(n):
        b = codes.gradient_code(n, s, seed=3)
        assert all(set(np.flatnonzero(b[i])) == set(codes.shards_of(i, n, s)) for i in range(n)), "cyclic support"
        coded = b @ gradients
        for used in itertools.combinations(range(n), n - s):
            a, _ = codes.gradient_decoder(b, list(used))
            full = a @ coded[list(used)]
            assert np.allclose(full, gradients.sum(axis=0), rtol=1e-9, atol=1e-9), (n, s, used)
        if s:
            with pytest.raises(codes.CodeError, match="cannot give the full gradient"):
                codes.gradient_decoder(b, list(range(n - s - 1)))


def _options(**overrides):
    base = dict(seed=0, m=10, n=20, l=2, a_path=None, save_results=True, allocation="equal", on_missing="incomplete",
                code_k=0, code_s=1, code_redundancy=1.5, batch_units=1, replan_every=0, learning_rate=0.05,
                data=str(SHARED_DATA / "forestfires.csv"))
    return SimpleNamespace(**{**base, **overrides})


def _ranks(task_class, options, workers: int, shares=None):
    master, ranks = task_class(options), {}
    bounds = kernels.split_rows(master.rows(), shares or [1.0] * workers)
    master.split(bounds)
    for rank in range(1, workers + 1):
        ranks[rank] = task_class(options)
        ranks[rank].split(bounds)
        ranks[rank].take_block(rank)
    return master, ranks


def test_the_mds_task_decodes_a_times_b_from_whichever_k_answer_first():
    options = _options(m=11)  # 11 rows in k = 3 blocks: one zero row of padding
    master, ranks = _ranks(MdsMatmul, options, 4)
    assert master.k == 3
    for iteration, arrival in enumerate([(1, 2, 3, 4), (4, 3, 2), (2, 4, 1), (3, 4, 1)]):
        payload = master.next_input(iteration)
        answers = {}
        for rank in arrival:
            answers[rank] = ranks[rank].work(payload)
            if master.enough(answers):
                break
        record = master.combine(iteration, payload, answers)
        assert record["complete"] and record["decoded_from"] == list(arrival[:3])
        expected = master.a @ payload.reshape(20, 2)
        assert np.linalg.norm(master.saved[f"C_{iteration}"] - expected) <= 1e-9 * np.linalg.norm(expected)
    record = master.combine(9, payload, {1: answers[1], 4: answers[4]})
    assert record == {"complete": False, "decoded_from": [1, 4]}, "two of k = 3: no decode, said"


@pytest.mark.skipif(not (SHARED_DATA / "forestfires.csv").exists(), reason="the Forest Fires CSV is absent")
@pytest.mark.parametrize("straggler", [None, 1, 3])
def test_gradient_coded_training_steps_as_uncoded_training_with_everyone(straggler):
    """With one of three workers missing each iteration (or none), the coded steps are uncoded gradient descent's
    over all the rows, to floating-point rounding."""
    options = _options()
    master, ranks = _ranks(GradientCodedLinreg, options, 3)
    reference, reference_ranks = _ranks(Linreg, options, 3)
    for iteration in range(50):
        w = master.next_input(iteration)
        answers = {r: ranks[r].work(w) for r in (3, 2, 1) if r != straggler}
        record = master.combine(iteration, w, answers)
        uncoded = reference.combine(iteration, w, {r: reference_ranks[r].work(w) for r in (1, 2, 3)})
        assert record["complete"] and record["cost"] == pytest.approx(uncoded["cost"], rel=1e-12)
        assert np.allclose(master.w, reference.w, rtol=1e-10, atol=1e-13)
    short = master.combine(50, master.w, {1: ranks[1].work(master.w)})
    assert not short["complete"] and "the full gradient needs 2" in short["decode_error"]


def _batches_in_order(task, payload):
    """A worker's answers as the runner merges them: one per batch, in batch order."""
    return [task.work_batch(payload, j) for j in range(task.batches())]


@pytest.mark.parametrize("batch_units", [1, 2])
def test_bpcc_decodes_once_any_k_units_arrived_from_whichever_batches(batch_units):
    """A (9, 6) code over 3 workers holding 4, 3 and 2 units (unequal, as an allocation by speed makes them): every
    way the batches can arrive (each worker's in order, interleaved, cut off anywhere) decodes A B exactly as soon as
    6 units are in, and not before."""
    options = _options(m=11, code_k=6, batch_units=batch_units)  # 11 rows in 6 blocks of 2: one zero row
    master, ranks = _ranks(BpccMatmul, options, 3, shares=[4, 3, 2])
    assert master.units == 9 and master.bounds == [(0, 4), (4, 7), (7, 9)]
    payload = master.next_input(0)
    expected = master.a @ payload.reshape(20, 2)
    batches = {r: _batches_in_order(ranks[r], payload) for r in ranks}
    decodes = 0
    for taken in itertools.product(*(range(len(batches[r]) + 1) for r in (1, 2, 3))):
        for order in itertools.permutations((1, 2, 3)):
            answers = {}
            for rank, count in zip(order, (taken[r - 1] for r in order), strict=True):
                for answer in batches[rank][:count]:
                    answers[rank] = answer if rank not in answers else Answer(
                        np.concatenate([answers[rank].values, answer.values]), 0)
            units = sum(a.values.size for a in answers.values()) // (2 * 2)
            assert master.enough(answers) == (units >= 6)
            record = master.combine(0, payload, answers)
            assert record["complete"] == (units >= 6) and record["units"] == [
                answers[r].values.size // 4 if r in answers else 0 for r in (1, 2, 3)]
            if record["complete"]:
                decodes += 1
                assert np.linalg.norm(master.saved["C_0"] - expected) <= 1e-9 * np.linalg.norm(expected), taken
    assert decodes > 0


def test_bpcc_refuses_a_code_past_its_condition_bound_and_reassigning():
    with pytest.raises(codes.CodeError, match="condition number"):
        BpccMatmul.check_workers(_options(m=100, code_k=12, code_redundancy=2.0), 3)
    with pytest.raises(codes.CodeError, match="only 5 rows"):
        BpccMatmul.check_workers(_options(m=5, code_k=6), 3)
    with pytest.raises(BadInput, match="reassign"):
        BpccMatmul.check(_options(on_missing="reassign"))
