"""What happened on each worker's link in one iteration of the MPI job, and the job's pace."""

from __future__ import annotations


def iterations_per_min(count: int, first_start_s: float, last_end_s: float) -> float | None:
    """The job's pace as the report, the progress line and the view give it (the view's page repeats it in
    view.js): iterations over the simulated span from the first one's start to the last one's end."""
    span_s = last_end_s - first_start_s
    return 60.0 * count / span_s if count > 0 and span_s > 0 else None


class IterationLinks:
    """One list per field (index = rank - 1): the iteration record keeps this columnar shape, which is also the
    cheapest to encode at thousands of iterations a second."""

    FIELDS = ("distance_m", "rate_bps", "loss", "absent", "bytes_down", "bytes_up", "down_s", "up_s", "compute_s")

    def __init__(self, workers: int):
        self.distance_m: list = [None] * workers
        self.rate_bps: list = [None] * workers
        self.loss: list = [None] * workers  # the emulated link's packet loss (sleep emulation)
        self.absent: list = [None] * workers  # None = present, else why (kinds.ITERATION's workers.absent)
        self.bytes_down = [0] * workers
        self.bytes_up = [0] * workers
        self.down_s = [0.0] * workers
        self.up_s = [0.0] * workers
        self.compute_s: list = [None] * workers
        self.phy_bps: list = [0.0] * workers  # the emulated link's PHY rate, for a medium charging per frame

    def present(self, rank: int) -> bool:
        return self.absent[rank - 1] is None

    def record(self, ranks: list[int], vehicles: list[str]) -> dict:
        out = {"rank": ranks, "vehicle": vehicles, "present": [a is None for a in self.absent]}
        out.update((name, getattr(self, name)) for name in self.FIELDS)
        return out
