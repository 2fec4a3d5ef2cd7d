"""Linear regression with gradient coding (issue 30; Tandon et al., ICML 2017; nac_onboard.compute.codes): the rows
in one shard per worker, worker i holding shards i..i+s (mod N) and answering one coded combination of their
gradient sums (and squared-residual sums); from the first N - s answers the master recovers the full gradient and
steps, waiting for no more (`--code-s S` stragglers tolerated, default 1). With everyone present the steps are
uncoded gradient descent's, to floating-point rounding. With fewer than N - s answers there is no full gradient:
the weights stay as they were and the record says why.

Iteration record fields: `decoded_from` (ranks, in arrival order), `decode_s` (wall seconds), and `decode_error`
when the answers could not give the full gradient. Run summary: `code` (N, s)."""

from __future__ import annotations

import time

import numpy as np

from nac_onboard.compute import codes, kernels
from nac_onboard.compute.task import Answer
from nac_onboard.compute.tasks.linreg import Linreg
from nac_onboard.errors import BadInput


class GradientCodedLinreg(Linreg):
    name = "linreg_gc"
    replans = False  # the code fixes every worker's block
    default_iterations = 200
    summary = ("linreg with gradient coding (--code-s S stragglers): each worker holds S + 1 shards, the master "
               "recovers the full gradient from the first N - S answers")

    def __init__(self, options):
        super().__init__(options)  # every rank keeps the whole data set: a worker takes its s + 1 shards of it
        self.s = options.code_s
        self.b = np.zeros((0, 0))
        self.shards: list[tuple[int, int]] = []
        self.held: list[tuple[float, np.ndarray, np.ndarray]] = []  # (coefficient, X_j, y_j) of this worker's shards

    @classmethod
    def check(cls, options) -> None:
        super().check(options)
        if options.allocation != "equal" or options.replan_every:
            raise BadInput(f"--allocation {options.allocation}, --replan-every {options.replan_every}: gradient "
                           "coding's shards are equal and fixed (each worker holds s + 1)")

    @classmethod
    def check_workers(cls, options, workers: int) -> None:
        if not 0 <= options.code_s < workers:
            raise codes.CodeError(f"--code-s {options.code_s}: gradient coding with {workers} workers tolerates "
                                  f"0 <= s < {workers} stragglers")

    def split(self, bounds: list[tuple[int, int]]) -> None:
        super().split(bounds)
        workers = len(bounds)
        self.shards = kernels.split_rows(self.total_rows, [1.0] * workers)
        self.b = codes.gradient_code(workers, self.s, self.options.seed)

    def take_block(self, rank: int) -> None:
        workers = len(self.bounds)
        self.held = [(float(self.b[rank - 1, j]), self.x[start:stop], self.y[start:stop])
                     for j in codes.shards_of(rank - 1, workers, self.s) for start, stop in [self.shards[j]]]

    def work(self, payload: np.ndarray, extra_rows: int | None = None) -> Answer:
        coded, coded_sse = np.zeros(len(payload)), 0.0
        for coefficient, x, y in self.held:
            gradient, sse, _ = kernels.local_gradient(x, y, payload)
            coded += coefficient * gradient
            coded_sse += coefficient * sse
        return Answer(coded, self.total_rows, coded_sse)

    def enough(self, answers: dict[int, Answer]) -> bool:
        return len(answers) >= len(self.bounds) - self.s  # any N - s give the full gradient

    def combine(self, iteration: int, payload: np.ndarray, answers: dict[int, Answer]) -> dict:
        needed = len(self.bounds) - self.s
        used = list(answers)[:needed]
        record = {"decoded_from": used, "rows_used": 0, "cost": None, "complete": False}
        if len(used) < needed:
            record["decode_error"] = f"{len(used)} answers; the full gradient needs {needed}"
            return record
        t0 = time.perf_counter()
        try:
            a, _ = codes.gradient_decoder(self.b, [r - 1 for r in used])
        except codes.CodeError as err:
            record["decode_error"] = str(err)
            return record
        gradient = sum(weight * answers[r].values for weight, r in zip(a, used, strict=True))
        sse = float(sum(weight * answers[r].sse for weight, r in zip(a, used, strict=True)))
        record["decode_s"] = time.perf_counter() - t0
        self.w = payload - self.options.learning_rate * gradient / self.total_rows
        self.cost = sse / (2 * self.total_rows)
        record.update(cost=self.cost, rows_used=self.total_rows, complete=True)
        return record

    def final(self) -> dict:
        return {**super().final(), "code": f"gradient coding, N = {len(self.bounds)}, s = {self.s} (cyclic)"}
