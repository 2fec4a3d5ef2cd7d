"""The Task interface of the MPI job: one module per task in nac_onboard/compute/tasks/ implements it, and the
runner (master and workers, sends, deadlines, absences, records) works for any of them.

A task splits `rows()` rows among the workers (contiguous blocks, `bounds`). Each iteration the master sends
every present worker the same input (`next_input`), each worker answers with `work()` on its block, and the
task's `iterate` combines what arrived (it may send more, as matmul's re-assignment does).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar, Protocol

import numpy as np

from nac_onboard.compute.iteration import IterationLinks


class Master(Protocol):
    """What a task's master side may ask of the runner."""

    workers: list[int]  # worker ranks
    bounds: list[tuple[int, int]]  # each worker's rows [start, stop), by rank - 1

    def send_all(self, ranks: list[int], iteration: int, payload: np.ndarray, links: IterationLinks) -> None: ...

    def send_extra(self, rank: int, iteration: int, payload: np.ndarray, extra_rows: int,
                   links: IterationLinks) -> None: ...

    def collect(self, iteration: int, waiting: set[int], links: IterationLinks,
                deadline: float) -> dict[int, np.ndarray]: ...

    def receive_from(self, rank: int, deadline: float) -> np.ndarray | None: ...

    def write_pending(self) -> None: ...


class Task(ABC):
    name: ClassVar[str]  # the --task value
    default_iterations: ClassVar[int]
    summary: ClassVar[str]  # one line for --help

    def __init__(self, options):
        self.options = options  # ComputeOptions

    @classmethod
    @abstractmethod
    def check(cls, options) -> None:
        """Refuse bad options or data before MPI starts (raise BadInput naming the file, line or option)."""

    # ---- both sides ---------------------------------------------------------------------------------------------
    @abstractmethod
    def rows(self) -> int:
        """Rows shared out among the workers."""

    @abstractmethod
    def input_floats(self) -> int:
        """Floats in one iteration's input (what the warm-up exchange sends)."""

    @abstractmethod
    def largest_input(self, bounds: list[tuple[int, int]]) -> int:
        """Floats in the largest payload a worker can receive."""

    @abstractmethod
    def largest_result(self, bounds: list[tuple[int, int]]) -> int:
        """Floats in the largest result a worker can send."""

    # ---- worker -----------------------------------------------------------------------------------------------
    @abstractmethod
    def take_block(self, start: int, stop: int) -> None:
        """Keep this worker's rows [start, stop)."""

    @abstractmethod
    def work(self, extra: bool, payload: np.ndarray, extra_rows: int) -> tuple[np.ndarray, int, float]:
        """(result, rows used, sum of squared errors or 0) for one input; `extra`: re-assigned rows in payload."""

    # ---- master -----------------------------------------------------------------------------------------------
    @abstractmethod
    def iterate(self, master: Master, iteration: int, present: list[int], links: IterationLinks,
                t_start: float) -> dict:
        """Send this iteration's input to the present workers, combine what arrives; the iteration record's
        task fields, with `complete` (every row's result arrived)."""

    def results(self) -> dict[str, np.ndarray]:
        """Arrays for results.npz at the end (empty: no file)."""
        return {}

    def final(self) -> dict:
        """The run summary's task fields."""
        return {}
