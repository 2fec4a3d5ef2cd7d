"""One clock for a run: simulated seconds, and how long they last on the wall clock.

On a vehicle, simulated time is wall time. In SITL at `--speedup X` the simulator's clock runs X times faster
than the wall clock, and so must everything timed against it: the experiment runner publishes its clock in a
small JSON file named by $NAC_SIM_CLOCK (speed-up, a simulated time and the monotonic time it was read), and
every process of the run (agents, MPI ranks) reads it. A transfer or a timeout of T simulated seconds then waits
T / X wall seconds, and records carry simulated times next to wall times, so results in simulated seconds do not
depend on the speed-up. CLOCK_MONOTONIC is the same in every network namespace, so the file means the same
thing to a process inside a simulated companion.

The published `speedup` is the simulator's measured pace, not the one asked for: a simulator that cannot keep
up (many vehicles on two cores) runs slower than --speedup, and rates or timeouts scaled by the nominal value
would then be too fast in simulated time. Readers extrapolate from the last sample and never go back in time.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections import deque
from dataclasses import dataclass

from nac_onboard.errors import BadInput

ENV = "NAC_SIM_CLOCK"
REFRESH_S = 0.1  # wall seconds between re-reads of the published clock: between them a reader extrapolates at the
# last pace, and a simulator slowed by load meanwhile puts it ahead (0.5 s let a 5x run's .tlog run 5 % fast)


class ClockError(BadInput):
    pass


def slowed_s(wall_s: float, speedup: float) -> float:
    """A wait or timeout of wall_s stretched below 1x, where what it waits for comes on the run's slowed clock (a
    1 Hz heartbeat is 10 wall seconds apart at 0.1x); above 1x it stays wall seconds, a floor a loaded host's late
    wake-ups need."""
    return wall_s / min(speedup, 1.0)


@dataclass(frozen=True)
class ClockSample:
    speedup: float
    sim_s: float
    mono_s: float


class Clock:
    """Wall time: a real vehicle's, and SITL's without a published clock."""

    speedup = 1.0
    simulated = False

    def now_s(self) -> float:
        """Seconds on the run's time axis (unix time here)."""
        return time.time()

    def wall_s(self, sim_duration_s: float) -> float:
        """How long sim_duration_s of the run's time lasts on the wall clock."""
        return sim_duration_s / self.speedup

    def sim_s(self, wall_duration_s: float) -> float:
        return wall_duration_s * self.speedup


class SharedClock(Clock):
    """The simulator's clock, as the runner publishes it."""

    simulated = True

    def __init__(self, path: str):
        self.path = path
        self._sample = read_sample(path)
        self._read_at = time.monotonic()
        self._last_s = -math.inf

    @property
    def speedup(self) -> float:
        self._refresh(time.monotonic())
        return self._sample.speedup

    def _refresh(self, mono: float) -> None:
        if mono - self._read_at >= REFRESH_S:
            self._read_at = mono
            try:
                self._sample = read_sample(self.path)
            except ClockError:
                pass  # keep the last sample rather than fail mid-record

    def now_s(self) -> float:
        mono = time.monotonic()
        self._refresh(mono)
        s = self._sample
        self._last_s = max(self._last_s, s.sim_s + (mono - s.mono_s) * s.speedup)
        return self._last_s


def read_sample(path: str) -> ClockSample:
    try:
        with open(path) as f:
            values = json.load(f)
        sample = ClockSample(float(values["speedup"]), float(values["sim_s"]), float(values["mono_s"]))
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise ClockError(f"{path} (${ENV}): not a published clock ({err})") from None
    if not (math.isfinite(sample.speedup) and sample.speedup > 0 and math.isfinite(sample.sim_s)
            and math.isfinite(sample.mono_s)):
        raise ClockError(f"{path} (${ENV}): speedup must be > 0 and times finite, got {sample}")
    return sample


def publish(path: str, speedup: float, sim_s: float) -> None:
    """Write the clock atomically: readers see the old sample or the new one, never half of one."""
    partial = f"{path}.partial"
    with open(partial, "w") as f:
        json.dump({"speedup": speedup, "sim_s": sim_s, "mono_s": time.monotonic()}, f)
    os.replace(partial, path)


class Pace:
    """The simulator's measured pace (simulated seconds per wall second) over the last `window_s` of samples;
    the nominal speed-up until there are enough, and never above PACE_LIMIT times it."""

    def __init__(self, nominal: float, window_s: float = 1.0):
        self.nominal, self.window_s = nominal, window_s
        self._samples: deque[tuple[float, float]] = deque()

    def add(self, sim_s: float, mono_s: float | None = None) -> float:
        mono_s = time.monotonic() if mono_s is None else mono_s
        self._samples.append((mono_s, sim_s))
        while len(self._samples) > 2 and mono_s - self._samples[1][0] >= self.window_s:
            self._samples.popleft()
        return self.value()

    def value(self) -> float:
        if len(self._samples) < 2 or self._samples[-1][0] - self._samples[0][0] < self.window_s / 2:
            return self.nominal
        (m0, s0), (m1, s1) = self._samples[0], self._samples[-1]
        return min(max((s1 - s0) / (m1 - m0), self.nominal * 0.01), self.nominal * PACE_LIMIT)


PACE_LIMIT = 1.25  # a simulator catching up after a stall briefly runs faster than asked


def from_env() -> Clock:
    path = os.environ.get(ENV)
    return SharedClock(path) if path else Clock()
