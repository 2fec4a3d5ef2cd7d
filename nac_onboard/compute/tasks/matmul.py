"""Matrix multiplication AB (DESIGN.md 5): A (m x n) split by rows, block A_i kept by worker i; B (n x l) is the
input sent each iteration; the master stacks the A_i B. A missing block is re-assigned to a worker that answered
(`--on-missing reassign`: its rows of A travel with B) or the iteration is incomplete."""

from __future__ import annotations

import os

import numpy as np

from nac_onboard.compute import kernels
from nac_onboard.compute.iteration import IterationLinks
from nac_onboard.compute.messages import RESULT_HEADER, RESULT_ITERATION
from nac_onboard.compute.task import Master, Task
from nac_onboard.errors import BadInput


def matmul_inputs(seed: int, m: int, n: int, a_path: str | None = None):
    """A (m x n) from the seed or a .npy file, and the generator of the B (n x l) sent each iteration."""
    rng = np.random.default_rng(seed)
    a = np.load(a_path) if a_path else rng.standard_normal((m, n))
    return a, np.random.default_rng(seed + 1)


class Matmul(Task):
    name = "matmul"
    default_iterations = 40
    summary = "A (m x n) by rows among the workers, B (n x l) sent each iteration, the master stacks A_i B"

    def __init__(self, options):
        super().__init__(options)
        self.a, self.b_rng = matmul_inputs(options.seed, options.m, options.n, options.a_path)
        self.block = self.a
        self.saved: dict[str, np.ndarray] = {}  # --save-results

    @classmethod
    def check(cls, options) -> None:
        for name in ("m", "n", "l"):
            if getattr(options, name) < 1:
                raise BadInput(f"--{name} must be >= 1")
        if options.a_path and not os.path.isfile(options.a_path):
            raise BadInput(f"--a {options.a_path}: no such file")

    def rows(self) -> int:
        return len(self.a)

    def input_floats(self) -> int:
        return self.options.n * self.options.l

    def largest_input(self, bounds: list[tuple[int, int]]) -> int:
        return max(stop - start for start, stop in bounds) * self.options.n + self.input_floats()

    def largest_result(self, bounds: list[tuple[int, int]]) -> int:
        return max(stop - start for start, stop in bounds) * self.options.l

    def take_block(self, start: int, stop: int) -> None:
        self.block = self.a[start:stop]

    def work(self, extra: bool, payload: np.ndarray, extra_rows: int) -> tuple[np.ndarray, int, float]:
        n, l = self.options.n, self.options.l  # noqa: E741 (the research's name for B's columns)
        if extra:
            a_rows, b = payload[:extra_rows * n].reshape(extra_rows, n), payload[extra_rows * n:]
            return kernels.matmul_block(a_rows, b.reshape(n, l)).ravel(), extra_rows, 0.0
        return kernels.matmul_block(self.block, payload.reshape(n, l)).ravel(), len(self.block), 0.0

    def iterate(self, master: Master, iteration: int, present: list[int], links: IterationLinks,
                t_start: float) -> dict:
        o = self.options
        b = self.b_rng.standard_normal((o.n, o.l))
        master.send_all(present, iteration, b.ravel(), links)
        master.write_pending()
        results = master.collect(iteration, set(present), links, master.deadline(t_start))
        blocks = {r: results[r][RESULT_HEADER:].reshape(-1, o.l) for r in results}
        record = {}
        missing = [r for r in master.workers if r not in blocks]
        if missing and o.on_missing == "reassign" and blocks:
            record["reassigned"] = self.reassign(master, iteration, b, missing, blocks, links,
                                                 master.deadline(t_start, 2))
        record["complete"] = all(r in blocks for r in master.workers)
        if record["complete"] and o.save_results:
            self.saved[f"B_{iteration}"] = b
            self.saved[f"C_{iteration}"] = kernels.stack_blocks([blocks[r] for r in master.workers])
        return record

    def reassign(self, master: Master, iteration: int, b: np.ndarray, missing: list[int], blocks: dict,
                 links: IterationLinks, deadline: float) -> list[dict]:
        """Send each missing block's rows of A, with B, to a worker that answered; wait for those answers."""
        helpers = [r for r in master.workers if r in blocks]
        plan: dict[int, list[int]] = {}
        for k, rank in enumerate(missing):
            helper = helpers[k % len(helpers)]
            start, stop = master.bounds[rank - 1]
            master.send_extra(helper, iteration, np.concatenate([self.a[start:stop].ravel(), b.ravel()]),
                              stop - start, links)
            plan.setdefault(helper, []).append(rank)
        done = []
        for helper, ranks in plan.items():
            for rank in ranks:
                answer = master.receive_from(helper, deadline)
                if answer is not None and int(answer[RESULT_ITERATION]) == iteration:
                    blocks[rank] = answer[RESULT_HEADER:].reshape(-1, self.options.l)
                    done.append({"rows_of": rank, "by": helper})
        return done

    def results(self) -> dict[str, np.ndarray]:
        return self.saved
