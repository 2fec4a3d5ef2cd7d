"""MDS-coded matrix multiplication (issue 30; nac_onboard.compute.codes): A (m x n) cut into k row blocks (padded
with zero rows to k equal blocks), encoded once into one coded block per worker by a systematic real generator;
each iteration every worker multiplies its coded block by the B sent, and the master decodes A B from the first k
results that arrive, waiting for no more (`--code-k K`, default: the workers less one, so any one may straggle).

Iteration record fields: `decoded_from` (the ranks whose results were decoded, in arrival order), `decode_s` (the
master's decode, wall seconds), `condition` (of the system solved; 1 for the systematic blocks alone). Run summary:
`code` (n, k and the generator) and `worst_condition` over every k of the n coded blocks."""

from __future__ import annotations

import math
import time

import numpy as np

from nac_onboard.compute import codes, kernels
from nac_onboard.compute.task import Answer
from nac_onboard.compute.tasks.matmul import Matmul
from nac_onboard.errors import BadInput


class MdsMatmul(Matmul):
    name = "matmul_mds"
    replans = False  # the code fixes every worker's block
    default_iterations = 40
    summary = ("matmul with A's row blocks MDS-coded (--code-k K of the N workers decode A B): the master decodes "
               "from the first K results")

    def __init__(self, options):
        super().__init__(options)
        self.k = 0
        self.generator = np.zeros((0, 0))
        self.block_rows = 0

    @classmethod
    def check(cls, options) -> None:
        super().check(options)
        if options.allocation != "equal" or options.on_missing != "incomplete" or options.replan_every:
            raise BadInput("matmul_mds: every coded block is the same size and any k decode: --allocation capacity, "
                           "speed, energy, --replan-every and --on-missing reassign are for the other matmuls")

    @staticmethod
    def code_k(options, workers: int) -> int:
        return options.code_k or max(workers - 1, 1)

    @classmethod
    def check_workers(cls, options, workers: int) -> None:
        k = cls.code_k(options, workers)
        if k > workers:
            raise codes.CodeError(f"--code-k {k}: a code needs k <= the {workers} workers (any k of them decode)")
        codes.check_mds(workers, k, options.m, "use fewer workers or another k")

    def split(self, bounds: list[tuple[int, int]]) -> None:
        super().split(bounds)
        workers = len(bounds)
        self.k = self.code_k(self.options, workers)
        self.generator = codes.mds_generator(workers, self.k)
        self.block_rows = -(-self.options.m // self.k)

    def largest_input(self) -> int:
        return self.input_floats()

    def largest_result(self) -> int:
        return self.block_rows * self.options.l

    def take_block(self, rank: int) -> None:
        self.block = codes.encode(self.generator[rank - 1:rank], codes.row_blocks(self.a, self.k))[0]

    def work(self, payload: np.ndarray, extra_rows: int | None = None) -> Answer:
        b = payload.reshape(self.options.n, self.options.l)
        return Answer(kernels.matmul_block(self.block, b).ravel(), self.block_rows)

    def enough(self, answers: dict[int, Answer]) -> bool:
        return len(answers) >= self.k

    def combine(self, iteration: int, payload: np.ndarray, answers: dict[int, Answer]) -> dict:
        if len(answers) < self.k:
            return {"complete": False, "decoded_from": sorted(answers)}
        used = list(answers)[:self.k]
        results = np.stack([answers[r].values.reshape(self.block_rows, self.options.l) for r in used])
        t0 = time.perf_counter()
        try:
            blocks, condition = codes.mds_decode(self.generator, [r - 1 for r in used], results)
        except codes.CodeError as err:  # checked at the start for every k-subset: kept as a record, not a crash
            return {"complete": False, "decoded_from": used, "decode_error": str(err)}
        product = blocks.reshape(-1, self.options.l)[:self.options.m]
        decode_s = time.perf_counter() - t0
        if self.options.save_results:
            self.saved[f"B_{iteration}"] = payload.reshape(self.options.n, self.options.l)
            self.saved[f"C_{iteration}"] = product
        return {"complete": True, "decoded_from": used, "decode_s": decode_s, "condition": condition}

    def final(self) -> dict:
        return {"code": f"({len(self.bounds)}, {self.k}) systematic, Cauchy parity",
                "worst_condition": codes.worst_condition(self.generator) if self.k else math.nan}
