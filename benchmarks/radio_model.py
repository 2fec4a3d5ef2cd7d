"""Cost of the radio model per step: 100 pairs stepped at 10 Hz as the kernel shaper steps them (positions in,
path loss, shadowing, fading, 802.11n rate and loss out), in CPU time; the target is under 2 % of a core.

    python benchmarks/radio_model.py [--pairs 100] [--seconds 60] [--smoke]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from nac_onboard.radio.air_link import AirRadio
from nac_onboard.radio.channel import PRESETS

import _common  # (benchmarks/_common.py, beside this script)

SMOKE = {"seconds": 2.0}
RATE_HZ = 10.0


def vehicles_for(pairs: int) -> int:
    """The smallest fleet with at least `pairs` pairs."""
    return math.ceil((1 + math.sqrt(1 + 8 * pairs)) / 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=100)
    parser.add_argument("--seconds", type=float, default=60.0, help="simulated seconds stepped at 10 Hz")
    parser.add_argument("--channel", default="wifi-flight")
    args = _common.parse_args(parser, SMOKE)
    n = vehicles_for(args.pairs)
    air = AirRadio(PRESETS[args.channel], n, seed=0)
    rng = np.random.default_rng(0)
    positions = rng.uniform(-20, 20, (n, 3)) + [0, 0, 23]
    velocity = rng.normal(0, 1.0, (n, 3)) * [1, 1, 0]
    steps = int(args.seconds * RATE_HZ)
    cpu0, wall0 = time.process_time(), time.perf_counter()
    for k in range(steps):
        positions = positions + velocity / RATE_HZ
        air.step(k / RATE_HZ, positions, positions[:, 2])
    cpu_s, wall_s = time.process_time() - cpu0, time.perf_counter() - wall0
    per_step_ms = cpu_s / steps * 1e3
    print(f"{args.channel}: {n} vehicles = {len(air.i)} pairs, {steps} steps at {RATE_HZ:g} Hz")
    print(f"  CPU per step {per_step_ms:.3f} ms (wall {wall_s / steps * 1e3:.3f} ms): "
          f"{per_step_ms * RATE_HZ / 10:.2f} % of a core at {RATE_HZ:g} Hz (target < 2 %)")


if __name__ == "__main__":
    main()
