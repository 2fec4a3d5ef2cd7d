"""Bounds that come from the sample a test has, so a measured quantity is judged only as far as its sample allows.

A median's confidence interval from order statistics (distribution-free: no assumption on how a loaded machine
spreads the measurements): with n samples, the k-th smallest and the k-th largest bound the median with at least the
stated confidence, k from the binomial(n, 1/2) distribution. A bin with too few samples gives no interval at all.
"""

from __future__ import annotations

import math

import numpy as np

#: below this, a median's 95 % interval is the whole sample's range (n = 5: k = 1) and says little: not judged
MIN_SAMPLES = 8


def median_interval(values, confidence: float = 0.95) -> tuple[float, float] | None:
    """(low, high) holding the population median with at least `confidence`, or None with fewer than MIN_SAMPLES."""
    x = np.sort(np.asarray(values, dtype=float))
    n = len(x)
    if n < MIN_SAMPLES:
        return None
    tail = (1.0 - confidence) / 2
    k, below = 0, 0.0
    while True:  # the largest k with P(Binomial(n, 1/2) < k) <= tail: x[k-1] and x[n-k] bound the median
        below_next = below + math.comb(n, k) / 2 ** n
        if below_next > tail:
            break
        below, k = below_next, k + 1
    k = max(k, 1)
    return float(x[k - 1]), float(x[n - k])


def agrees_within(values, target: float, rel: float, confidence: float = 0.95) -> bool | None:
    """Whether the sample's median can be within rel of target (its interval meets the band); None: too few."""
    interval = median_interval(values, confidence)
    if interval is None:
        return None
    low, high = interval
    return low <= target * (1 + rel) and high >= target * (1 - rel)
