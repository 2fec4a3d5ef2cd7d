"""Compute kernels of the research's two tasks (DESIGN.md 5), pure and rank-agnostic: the MPI runner sends the
inputs and combines the outputs; these functions know nothing of MPI and are tested in one process.

Linear regression: cost J(w) = 1/(2m) sum (Xw - y)^2, gradient 1/m X^T (Xw - y). A worker returns the *sums* over
its shard (X_i^T (X_i w - y_i) and its squared-residual sum) with its row count, so the master's combination of
whichever shards arrived is exact gradient descent on those rows, weighted by shard size.
"""

from __future__ import annotations

import numpy as np


def split_rows(rows: int, shares: list[float]) -> list[tuple[int, int]]:
    """Contiguous [start, stop) blocks of `rows` in proportion to shares (equal shares: as equal as possible)."""
    total = float(sum(shares))
    if rows < 0 or not shares or total <= 0 or min(shares) < 0:
        raise ValueError("need rows >= 0 and non-negative shares with a positive sum")
    bounds = np.rint(np.cumsum([0.0, *shares]) / total * rows).astype(int)
    bounds[-1] = rows
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def matmul_block(a_block: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a_block @ b


def stack_blocks(blocks: list[np.ndarray]) -> np.ndarray:
    return np.vstack(blocks)


def local_gradient(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, float, int]:
    """(X^T (Xw - y), sum of squared residuals, rows) over one shard."""
    residual = x @ w - y
    return x.T @ residual, float(residual @ residual), len(y)


def combine_gradients(parts: list[tuple[np.ndarray, float, int]]) -> tuple[np.ndarray, float, int]:
    """Gradient and cost over the union of the shards that arrived: (1/m sum g_i, 1/(2m) sum sse_i, m)."""
    rows = sum(p[2] for p in parts)
    if rows == 0:
        raise ValueError("no shard arrived")
    gradient = parts[0][0].copy()
    for part in parts[1:]:  # in order, as a sum over axis 0 would: the same floats, without stacking
        gradient += part[0]
    gradient /= rows
    return gradient, sum(p[1] for p in parts) / (2 * rows), rows


def gradient_descent(x: np.ndarray, y: np.ndarray, w0: np.ndarray, learning_rate: float,
                     iterations: int) -> tuple[np.ndarray, list[float]]:
    """Single-process reference: full-batch gradient descent; returns the weights and the cost before each step."""
    w, costs = w0.astype(float).copy(), []
    for _ in range(iterations):
        gradient, cost, _ = combine_gradients([local_gradient(x, y, w)])
        costs.append(cost)
        w -= learning_rate * gradient
    return w, costs
