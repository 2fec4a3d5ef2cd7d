"""What the master and the workers send each other: flat float64 arrays with a fixed header, so one posted receive
per peer can take any message. The header fields have names here; nothing reads them by bare position.

With --pad-bits every message ends in that many bits of zeros, which the receiving Inbox strips: over a shaped
kernel network (SITL), the channel model's per-transfer overhead then travels as real bytes through the links,
where the sleep emulation would have waited for it."""

from __future__ import annotations

import math

import numpy as np

TAG_WORK, TAG_RESULT = 1, 2
BITS_PER_FLOAT = 64

# master -> worker: [kind, iteration, rate_bps, extra_rows, loss | payload...] (rate and loss: the emulated link's)
KIND_WORK, KIND_EXTRA, KIND_STOP, KIND_WARMUP = 1.0, 2.0, 3.0, 4.0  # extra: re-assigned rows of A, then B
KIND_PLAN = 5.0  # the blocks re-planned: the payload is every worker's [start, stop), in rank order
WORK_KIND, WORK_ITERATION, WORK_RATE_BPS, WORK_EXTRA_ROWS, WORK_LOSS = 0, 1, 2, 3, 4
WORK_HEADER = 6


def work_header(kind: float, iteration: float = 0.0, rate_bps: float = 0.0, extra_rows: float = 0.0,
                loss: float = 0.0, phy_bps: float = 0.0) -> tuple[float, ...]:
    return (kind, iteration, rate_bps, extra_rows, loss, phy_bps)

# worker -> master: [iteration, compute_s, up_s, rows, sse, late, batch, more, late_s | result...] (rows, sse,
# result: the task's Answer; late: the worker's work segments so far that its host did more slowly than its device
# profile, on the run's clock, and late_s by how much in all, simulated; batch: the answer's place among the
# iteration's batches, more: whether more batches follow)
RESULT_ITERATION, RESULT_COMPUTE_S, RESULT_UP_S, RESULT_ROWS, RESULT_SSE, RESULT_LATE = 0, 1, 2, 3, 4, 5
RESULT_BATCH, RESULT_MORE, RESULT_LATE_S = 6, 7, 8
RESULT_HEADER = 9
WARMUP_ANSWER = (-1.0,) + (0.0,) * (RESULT_HEADER - 1)
STOPPED_ANSWER = (-2.0,) + (0.0,) * (RESULT_HEADER - 1)  # a worker's last message, after a STOP that finalizes


def pad_floats(pad_bits: float) -> int:
    return math.ceil(pad_bits / BITS_PER_FLOAT) if pad_bits > 0 else 0


def message(head, payload_floats: int, pad: int) -> np.ndarray:
    """A message buffer: the header filled, room for the payload after it, zeros for the pad at the end."""
    out = np.empty(len(head) + payload_floats + pad)
    out[:len(head)] = head
    if pad:
        out[-pad:] = 0.0
    return out
