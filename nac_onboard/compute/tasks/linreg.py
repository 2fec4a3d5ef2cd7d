"""Linear regression by gradient descent on the UCI Forest Fires data (DESIGN.md 5): the rows split into one shard
per worker; each iteration the master sends the weights, the workers return their shards' gradient sums, and the
master steps on whichever shards arrived (exact gradient descent over those rows, weighted by shard size)."""

from __future__ import annotations

import numpy as np

from nac_onboard.compute import forestfires, kernels
from nac_onboard.compute.task import Answer, Task, file_sha256, timed
from nac_onboard.errors import BadInput


class Linreg(Task):
    name = "linreg"
    default_iterations = 200
    summary = "gradient descent on Forest Fires, one shard of rows per worker, the master combines gradients"

    def __init__(self, options):
        super().__init__(options)
        self.x_all, self.y_all = forestfires.load(forestfires.find_csv(options.data))
        self.x, self.y = self.x_all, self.y_all  # a worker's shard once it takes one (again, when re-planned)
        self.total_rows = len(self.y)
        self.w = np.zeros(self.x.shape[1])
        self.cost: float | None = None

    @classmethod
    def check(cls, options) -> None:
        forestfires.load(forestfires.find_csv(options.data))  # every value checked before MPI starts

    @classmethod
    def inputs_of(cls, options) -> str:
        return f"data sha256 {file_sha256(forestfires.find_csv(options.data))}"

    def rows(self) -> int:
        return self.total_rows

    def input_floats(self) -> int:
        return self.x.shape[1]

    def largest_input(self) -> int:
        return self.x.shape[1]

    def largest_result(self) -> int:
        return self.x.shape[1]

    def row_cost(self) -> tuple[float, float]:
        """A gradient over every row, timed here (its result is one gradient whatever the rows: no bits per row)."""
        return timed(lambda: kernels.local_gradient(self.x_all, self.y_all, self.w)) / self.total_rows, 0.0

    def take_block(self, rank: int) -> None:
        start, stop = self.bounds[rank - 1]
        self.x, self.y = self.x_all[start:stop], self.y_all[start:stop]

    def work(self, payload: np.ndarray, extra_rows: int | None = None) -> Answer:
        gradient, sse, rows = kernels.local_gradient(self.x, self.y, payload)
        return Answer(gradient, rows, sse)

    def next_input(self, iteration: int) -> np.ndarray:
        return self.w

    def combine(self, iteration: int, payload: np.ndarray, answers: dict[int, Answer]) -> dict:
        if not answers:
            return {"cost": None, "rows_used": 0, "complete": False}
        gradient, cost, rows = kernels.combine_gradients([(a.values, a.sse, a.rows) for a in answers.values()])
        self.w = payload - self.options.learning_rate * gradient
        self.cost = cost
        return {"cost": cost, "rows_used": rows, "complete": rows == self.total_rows}

    def results(self) -> dict[str, np.ndarray]:
        return {"weights": self.w}

    def resume(self, arrays: dict[str, np.ndarray]) -> None:
        w = arrays.get("weights")
        if w is None or w.shape != self.w.shape or w.dtype.kind != "f" or not np.isfinite(w).all():
            raise BadInput(f"--resume: the checkpoint's weights: expected {self.w.size} finite numbers")
        self.w = w.astype(float)

    def final(self) -> dict:
        return {"final_cost": self.cost}
