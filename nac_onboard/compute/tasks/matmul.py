"""Matrix multiplication AB (DESIGN.md 5): A (m x n) split by rows, block A_i kept by worker i; B (n x l) is the
input sent each iteration; the master stacks the A_i B. A missing block is re-assigned to a worker that answered
(`--on-missing reassign`: its rows of A travel with B) or the iteration is incomplete."""

from __future__ import annotations

import os

import numpy as np

from nac_onboard.compute import kernels
from nac_onboard.compute.task import Answer, Extra, Task, file_sha256, timed
from nac_onboard.errors import BadInput


def matmul_inputs(seed: int, m: int, n: int, a_path: str | None = None) -> np.ndarray:
    """A (m x n) from the seed or a .npy file (each iteration's B: Matmul.next_input)."""
    return np.load(a_path) if a_path else np.random.default_rng(seed).standard_normal((m, n))


class Matmul(Task):
    name = "matmul"
    default_iterations = 40
    summary = "A (m x n) by rows among the workers, B (n x l) sent each iteration, the master stacks A_i B"

    def __init__(self, options):
        super().__init__(options)
        self.a = matmul_inputs(options.seed, options.m, options.n, options.a_path)
        self.block = self.a
        self.saved: dict[str, np.ndarray] = {}  # --save-results

    @classmethod
    def check(cls, options) -> None:
        for name in ("m", "n", "l"):
            if getattr(options, name) < 1:
                raise BadInput(f"--{name} must be >= 1")
        if options.a_path and not os.path.isfile(options.a_path):
            raise BadInput(f"--a {options.a_path}: no such file")

    @classmethod
    def inputs_of(cls, options) -> str:
        return f"A sha256 {file_sha256(options.a_path)}" if options.a_path else "A from the seed"

    def rows(self) -> int:
        return len(self.a)

    def input_floats(self) -> int:
        return self.options.n * self.options.l

    def _largest_block(self) -> int:
        """Rows in the largest block: any block may be all of A once re-planned (--replan-every)."""
        return self.rows() if self.options.replan_every else max(stop - start for start, stop in self.bounds)

    def largest_input(self) -> int:
        return self._largest_block() * self.options.n + self.input_floats()

    def largest_result(self) -> int:
        return self._largest_block() * self.options.l

    def row_cost(self) -> tuple[float, float]:
        """A's product with one B, timed here, per row; each row's result is l floats."""
        b = np.ones((self.options.n, self.options.l))
        return timed(lambda: kernels.matmul_block(self.a, b)) / len(self.a), 64.0 * self.options.l

    def take_block(self, rank: int) -> None:
        start, stop = self.bounds[rank - 1]
        self.block = self.a[start:stop]

    def work(self, payload: np.ndarray, extra_rows: int | None = None) -> Answer:
        n, l = self.options.n, self.options.l  # noqa: E741 (the research's name for B's columns)
        if extra_rows is not None:  # another worker's rows of A, then B
            a_rows, b = payload[:extra_rows * n].reshape(extra_rows, n), payload[extra_rows * n:]
            return Answer(kernels.matmul_block(a_rows, b.reshape(n, l)).ravel(), extra_rows)
        return Answer(kernels.matmul_block(self.block, payload.reshape(n, l)).ravel(), len(self.block))

    def next_input(self, iteration: int) -> np.ndarray:
        """B of this iteration: drawn from (seed, iteration), so a resumed master sends the B it would have sent."""
        rng = np.random.default_rng([self.options.seed + 1, iteration])
        return rng.standard_normal((self.options.n, self.options.l)).ravel()

    def plan_missing(self, iteration: int, payload: np.ndarray, missing: list[int],
                     answered: list[int]) -> list[Extra]:
        """--on-missing reassign: each missing block's rows of A, with B, to the workers that answered in turn."""
        if self.options.on_missing != "reassign" or not answered:
            return []
        plan = []
        for k, rank in enumerate(missing):
            start, stop = self.bounds[rank - 1]
            plan.append(Extra(answered[k % len(answered)], rank, np.concatenate([self.a[start:stop].ravel(), payload]),
                              stop - start))
        return plan

    def combine(self, iteration: int, payload: np.ndarray, answers: dict[int, Answer]) -> dict:
        ranks = [r for r in range(1, len(self.bounds) + 1) if self.bounds[r - 1][0] < self.bounds[r - 1][1]]
        complete = all(r in answers for r in ranks)  # every row's block (a worker planned out has none)
        if complete and self.options.save_results:
            self.saved[f"B_{iteration}"] = payload.reshape(self.options.n, self.options.l)
            self.saved[f"C_{iteration}"] = kernels.stack_blocks([answers[r].values.reshape(-1, self.options.l)
                                                                 for r in ranks])
        return {"complete": complete}

    def results(self) -> dict[str, np.ndarray]:
        return self.saved

    def resume(self, arrays: dict[str, np.ndarray]) -> None:
        """--save-results: the B and A B saved so far, kept in the next checkpoints."""
        self.saved = {name: value for name, value in arrays.items() if name[:2] in ("B_", "C_")}
