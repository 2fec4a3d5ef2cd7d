"""The Task contract of the MPI job. A task is one module in nac_onboard/compute/tasks/ (found there by name, the
--task value) and touches no MPI: the runner owns sending, deadlines, absences, retries and collecting.

The runner splits `rows()` into one block per worker (`split(bounds)` on every rank; worker rank r holds block
r - 1, `take_block`; the master may re-plan the blocks during the run, and every worker then splits and takes its
block again). Each iteration the master sends `next_input()` to the workers present, each answers with
`work()` on its block (a batched task: `work_batch()` for each of its `batches()`, each sent as it is done,
which the master merges in order), and after the deadline the master asks `plan_missing()` what to send again for
the blocks that did not arrive (by default nothing), collects those answers too, and `combine()`s everything that
arrived.
"""

from __future__ import annotations

import hashlib
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import ClassVar, NamedTuple

import numpy as np


class Answer(NamedTuple):
    """A worker's result on one block: what `work` returns and, for each block that arrived, `combine` receives."""

    values: np.ndarray
    rows: int  # data rows it covers
    sse: float = 0.0  # sum of squared errors, for a task that reports a cost


class Extra(NamedTuple):
    """A block sent again after it did not arrive: to worker `by`, which answers in place of worker `rows_of`."""

    by: int
    rows_of: int
    payload: np.ndarray
    rows: int  # travels with the payload; `work` gets it back as extra_rows


class Task(ABC):
    name: ClassVar[str]  # the --task value
    default_iterations: ClassVar[int]
    summary: ClassVar[str]  # one line for --help
    replans: ClassVar[bool] = True  # whether its blocks may be re-planned during the run (a code fixes them)

    def __init__(self, options):
        self.options = options  # ComputeOptions
        self.bounds: list[tuple[int, int]] = []  # each worker's rows [start, stop), by rank - 1

    @classmethod
    @abstractmethod
    def check(cls, options) -> None:
        """Refuse bad options or data before MPI starts (raise BadInput naming the file, line or option)."""

    @classmethod
    def check_workers(cls, options, workers: int) -> None:
        """Refuse what the number of workers makes impossible (a code needing more workers than there are), on
        every rank once MPI gives the size and before any work: raise ValueError saying why. Default: nothing."""
        return None

    # ---- both sides -----------------------------------------------------------------------------------------
    @abstractmethod
    def rows(self) -> int:
        """Rows shared out among the workers."""

    def row_cost(self) -> tuple[float, float]:
        """(this host's CPU seconds, result bits) per row of `rows()`: what `--allocation speed` weighs against each
        worker's device and link. Default: unknown (equal weight for the CPU, nothing for the link)."""
        return 1.0, 0.0

    def split(self, bounds: list[tuple[int, int]]) -> None:
        """The run's blocks, one per worker (rank r: bounds[r - 1]); called once on every rank, before the rest."""
        self.bounds = list(bounds)

    @abstractmethod
    def input_floats(self) -> int:
        """Floats in one iteration's input (what the warm-up exchange sends)."""

    @abstractmethod
    def largest_input(self) -> int:
        """Floats in the largest payload a worker can receive (an input or an Extra's)."""

    @abstractmethod
    def largest_result(self) -> int:
        """Floats in the largest result a worker can send."""

    # ---- worker ---------------------------------------------------------------------------------------------
    @abstractmethod
    def take_block(self, rank: int) -> None:
        """Keep worker `rank`'s block of the data (rows bounds[rank - 1])."""

    @abstractmethod
    def work(self, payload: np.ndarray, extra_rows: int | None = None) -> Answer:
        """The work on this worker's block for one input; with extra_rows, on an Extra's payload instead."""

    def batches(self) -> int:
        """Answers a worker sends per iteration: a batched task's worker sends each batch's result as soon as it is
        done (`work_batch`), so the master can use a slow worker's partial work. Default: one answer, `work`'s."""
        return 1

    def work_batch(self, payload: np.ndarray, batch: int) -> Answer:
        """Batch `batch` (0-based) of this worker's work for one input (a batched task only)."""
        raise NotImplementedError

    # ---- master ---------------------------------------------------------------------------------------------
    @abstractmethod
    def next_input(self, iteration: int) -> np.ndarray:
        """What every present worker gets this iteration (asked once per iteration, workers present or not)."""

    @abstractmethod
    def combine(self, iteration: int, payload: np.ndarray, answers: dict[int, Answer]) -> dict:
        """Combine the answers that arrived (by the rank whose block each covers, in arrival order); the
        iteration record's task fields, with `complete` (every row's result arrived)."""

    def enough(self, answers: dict[int, Answer]) -> bool:
        """Whether the answers so far (by rank, in arrival order) are all the iteration needs: a coded task
        decodes from the first k and does not wait for the rest. Default: every worker's answer is needed."""
        return False

    def plan_missing(self, iteration: int, payload: np.ndarray, missing: list[int],
                     answered: list[int]) -> list[Extra]:
        """What to send again for the blocks of the `missing` ranks, to ranks that `answered`: the runner sends
        these in order and waits for their answers until twice the timeout. Default: nothing."""
        return []

    def results(self) -> dict[str, np.ndarray]:
        """Arrays for results.npz (checkpoints and the end; empty: no file)."""
        return {}

    def resume(self, arrays: dict[str, np.ndarray]) -> None:
        """A restarted master's state from its checkpoint (what `results()` wrote, checked by the caller for its
        name only): raise BadInput saying what is wrong with it. Default: nothing to restore."""
        return None

    def final(self) -> dict:
        """The run summary's task fields."""
        return {}

    @classmethod
    def inputs_of(cls, options) -> str:
        """This rank's input files, as a fingerprint every rank's must match (a companion back with another data
        set computes another problem). Default: none."""
        return "no input files"


def file_sha256(path) -> str:
    """A file's sha256 (hex), or what kept it from being read."""
    digest = hashlib.sha256()
    try:
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                digest.update(chunk)
        return digest.hexdigest()
    except OSError as err:
        return f"unreadable ({err.strerror})"


def timed(work: Callable[[], object], repeats: int = 3) -> float:
    """The least of `repeats` CPU-time measurements of `work()` on this host, seconds."""
    best = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        work()
        best = min(best, time.process_time() - t0)
    return best
