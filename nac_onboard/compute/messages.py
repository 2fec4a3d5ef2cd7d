"""What the master and the workers send each other: flat float64 arrays with a fixed header, so one posted receive
per peer can take any message. The header fields have names here; nothing reads them by bare position."""

from __future__ import annotations

TAG_WORK, TAG_RESULT = 1, 2
BITS_PER_FLOAT = 64

# master -> worker: [kind, iteration, rate_bps, extra_rows | payload...]
KIND_WORK, KIND_EXTRA, KIND_STOP, KIND_WARMUP = 1.0, 2.0, 3.0, 4.0  # extra: re-assigned rows of A, then B
WORK_KIND, WORK_ITERATION, WORK_RATE_BPS, WORK_EXTRA_ROWS = 0, 1, 2, 3
WORK_HEADER = 4

# worker -> master: [iteration, compute_s, up_s, rows, sse | result...]
RESULT_ITERATION, RESULT_COMPUTE_S, RESULT_UP_S, RESULT_ROWS, RESULT_SSE = 0, 1, 2, 3, 4
RESULT_HEADER = 5
WARMUP_ANSWER = (-1.0, 0.0, 0.0, 0.0, 0.0)
