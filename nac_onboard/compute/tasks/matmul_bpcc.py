"""Batch-processing based coded matrix multiplication (issue 30), after the research group's BPCC (Wang, Xie, Lu, Wan
and Fu, "On Batch-Processing Based Coded Computing for Heterogeneous Distributed Computing Systems", IEEE Trans.
Netw. Sci. Eng. 2021): A's rows in k data blocks, encoded once into U = ceil(r k) coded units (the systematic
Cauchy code of nac_onboard.compute.codes; r: --code-redundancy), the units shared out among the workers by the run's
allocation (`--allocation speed`: each worker's expected units per second, from its device and its link). Each
iteration a worker multiplies its units by B in batches of --batch-units and sends each batch's products as soon as
they are done, so a slow worker's first batches count; the master decodes A B from the first k units to arrive,
from whichever workers, and waits for no more. A worker that finds the next iteration's input waiting between two
batches drops the rest (the iteration they were for is decoded).

Default k = 6 and r = 1.5: a (9, 6) code, worst condition number 281 over every 6 of its 9 units (measured); (12, 8)
is 5.5e3, (15, 10) 1.3e5, (18, 12) 2.7e6: larger codes are refused past codes.MAX_CONDITION.

Iteration record fields: `decoded_from` (the ranks whose units were decoded, in arrival order), `units` (units
received from each worker, rank order), `decode_s`, `condition`. Run summary: `code`, `worst_condition`."""

from __future__ import annotations

import math
import time

import numpy as np

from nac_onboard.compute import codes
from nac_onboard.compute.task import Answer, timed
from nac_onboard.compute.tasks.matmul import Matmul
from nac_onboard.errors import BadInput

DEFAULT_K = 6


class BpccMatmul(Matmul):
    name = "matmul_bpcc"
    default_iterations = 40
    summary = ("matmul with A's row blocks coded into units shared out by each worker's speed, sent back in batches "
               "(BPCC): the master decodes from the first --code-k units, from any workers")

    def __init__(self, options):
        super().__init__(options)
        self.k = self.code_k(options)
        self.units = self.code_units(options)
        self.block_rows = -(-options.m // self.k)
        self.generator = codes.mds_generator(self.units, self.k)
        self.data_blocks = codes.row_blocks(self.a, self.k)
        self.coded = np.zeros((0, self.block_rows, options.n))

    @staticmethod
    def code_k(options) -> int:
        return options.code_k or min(DEFAULT_K, options.m)

    @classmethod
    def code_units(cls, options) -> int:
        return math.ceil(options.code_redundancy * cls.code_k(options) - 1e-9)

    @classmethod
    def check(cls, options) -> None:
        super().check(options)
        if options.on_missing != "incomplete":
            raise BadInput("matmul_bpcc: any k units decode, from any workers: --on-missing reassign is for the "
                           "uncoded matmul")

    @classmethod
    def check_workers(cls, options, workers: int) -> None:
        """The code, which any number of workers can hold (a worker may hold no unit): k within A's rows, and every
        k of its units decodable within codes.MAX_CONDITION."""
        codes.check_mds(cls.code_units(options), cls.code_k(options), options.m,
                        "use a smaller --code-k or --code-redundancy")

    def rows(self) -> int:
        return self.units  # what is shared out: coded units, not A's rows

    def largest_input(self) -> int:
        return self.input_floats()

    def largest_result(self) -> int:
        return self.options.batch_units * self.block_rows * self.options.l

    def row_cost(self) -> tuple[float, float]:
        """(this host's CPU seconds, result bits) per coded unit: what `--allocation speed` weighs."""
        b = np.ones((self.options.n, self.options.l))
        return timed(lambda: self.data_blocks[0] @ b), 64.0 * self.block_rows * self.options.l

    def take_block(self, rank: int) -> None:
        start, stop = self.bounds[rank - 1]
        self.coded = codes.encode(self.generator[start:stop], self.data_blocks)

    def batches(self) -> int:
        return -(-len(self.coded) // self.options.batch_units)

    def work(self, payload: np.ndarray, extra_rows: int | None = None) -> Answer:
        return self.work_batch(payload, 0)

    def work_batch(self, payload: np.ndarray, batch: int) -> Answer:
        units = self.coded[batch * self.options.batch_units:(batch + 1) * self.options.batch_units]
        b = payload.reshape(self.options.n, self.options.l)
        return Answer(np.matmul(units, b).ravel(), len(units) * self.block_rows)

    def _unit_floats(self) -> int:
        return self.block_rows * self.options.l

    def enough(self, answers: dict[int, Answer]) -> bool:
        return sum(a.values.size for a in answers.values()) >= self.k * self._unit_floats()

    def combine(self, iteration: int, payload: np.ndarray, answers: dict[int, Answer]) -> dict:
        size = self._unit_floats()
        received = {rank: a.values.size // size for rank, a in answers.items()}
        units = [received.get(r, 0) for r in range(1, len(self.bounds) + 1)]
        available = [(self.bounds[rank - 1][0] + j, rank, answers[rank].values[j * size:(j + 1) * size])
                     for rank, count in received.items() for j in range(count)]
        if len(available) < self.k:
            return {"complete": False, "decoded_from": sorted(received), "units": units}
        # the data blocks' own units first: with all of them the decode is a copy, and the fewer parity units the
        # better the system's condition
        order = sorted(range(len(available)), key=lambda i: (available[i][0] >= self.k, i))
        used = [available[i] for i in order[:self.k]]
        decoded_from = list(dict.fromkeys(rank for _, rank, _ in used))
        t0 = time.perf_counter()
        try:
            blocks, condition = codes.mds_decode(self.generator, [u[0] for u in used],
                                                 np.stack([u[2].reshape(self.block_rows, -1) for u in used]))
        except codes.CodeError as err:  # checked at the start for every k-subset: kept as a record, not a crash
            return {"complete": False, "decoded_from": decoded_from, "units": units, "decode_error": str(err)}
        product = blocks.reshape(-1, self.options.l)[:self.options.m]
        decode_s = time.perf_counter() - t0
        if self.options.save_results:
            self.saved[f"B_{iteration}"] = payload.reshape(self.options.n, self.options.l)
            self.saved[f"C_{iteration}"] = product
        return {"complete": True, "decoded_from": decoded_from, "units": units, "decode_s": decode_s,
                "condition": condition}

    def final(self) -> dict:
        return {"code": f"({self.units}, {self.k}) systematic, Cauchy parity, batches of "
                        f"{self.options.batch_units} unit(s)",
                "worst_condition": codes.worst_condition(self.generator)}
