"""The companion's CPU: a device profile, and each rank's work stretched to that device's time on the run's clock.

A rank measures the CPU seconds its own work takes on this host (`time.process_time`: what a loaded host's other
processes take is not counted) and holds the result until `slowdown` times that has passed on the run's clock. So
a job that computes on a Jetson that is 6 times slower than this host takes the Jetson's time in simulated
seconds, at 1x as at any speed-up up to about the slowdown: above that the host's own time is longer than the
device's, the segment comes out late, and the run counts it (`late_cpu_segments`).

The slowdown is the device's CPU time over this host's for the job's work. It is measured, not looked up: `nac-onboard
bench` times the task's work here and on the companion, and the ratio goes into a profile file with who
measured it and where (NAC ships no Jetson figures: none we could find measures this work).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

import tomllib

from nac_onboard.errors import BadInput
from nac_onboard.inputs import MAX_CONFIG_BYTES, check_regular_file

SLOWDOWN_RANGE = (1.0, 1000.0)  # a companion slower than this host (down to a microcontroller's ~1000x); a faster
# one cannot be emulated by holding results back, so 1.0 (no stretch) is the floor


@dataclass(frozen=True)
class DeviceProfile:
    name: str
    slowdown: float  # the device's CPU seconds per CPU second of this host, for the job's work
    source: str  # who measured it, on what, how


HOST = DeviceProfile("host", 1.0, "this machine: no stretch")


def load_device_profile(path: str | Path) -> DeviceProfile:
    """A [device] table: name, slowdown (in SLOWDOWN_RANGE) and source (required: a figure without one is not used)."""
    path = Path(path)
    check_regular_file(path, "device profile", MAX_CONFIG_BYTES)
    try:
        table = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise BadInput(f"{path}: not TOML ({err})") from err
    device = table.get("device")
    if not isinstance(device, dict):
        raise BadInput(f"{path}: expected a [device] table with name, slowdown and source")
    name, source, slowdown = device.get("name"), device.get("source"), device.get("slowdown")
    if not isinstance(name, str) or not name.strip():
        raise BadInput(f"{path}: [device] name: expected a non-empty string")
    if not isinstance(source, str) or not source.strip():
        raise BadInput(f"{path}: [device] source: expected who measured the slowdown, on what and how")
    low, high = SLOWDOWN_RANGE
    if isinstance(slowdown, bool) or not isinstance(slowdown, int | float) or not math.isfinite(slowdown) \
            or not low <= slowdown <= high:
        raise BadInput(f"{path}: [device] slowdown: expected a number in {low:g}..{high:g} (the device's CPU "
                       f"seconds per CPU second of this host), got {slowdown!r}")
    unknown = sorted(set(device) - {"name", "slowdown", "source"})
    if unknown:
        raise BadInput(f"{path}: [device] has unknown fields {unknown}; expected name, slowdown, source")
    return DeviceProfile(name.strip(), float(slowdown), source.strip())


class CpuStretch:
    """Time one segment of a rank's work (`begin` ... `hold`) as the device would take it on the run's clock."""

    def __init__(self, slowdown: float, clock):
        self.slowdown, self.clock = slowdown, clock
        self.late = 0  # segments whose host time on the run's clock was already longer than the device's
        self._cpu0 = self._wall0 = 0.0

    @property
    def active(self) -> bool:
        return self.slowdown > 1.0

    def begin(self) -> None:
        self._cpu0, self._wall0 = time.process_time(), time.monotonic()

    def hold(self) -> float:
        """Wait until the device would have finished; its time for the segment in simulated seconds."""
        device_s = (time.process_time() - self._cpu0) * self.slowdown
        remaining_wall_s = self.clock.wall_s(device_s) - (time.monotonic() - self._wall0)
        if remaining_wall_s > 0:
            time.sleep(remaining_wall_s)
        else:
            self.late += 1
        return device_s


@dataclass(frozen=True)
class BenchResult:
    task: str
    workers: int
    iterations: int
    master_cpu_s: float  # per iteration: the task's input and combine
    worker_cpu_s: float  # per iteration: one worker's work on its block

    @property
    def cpu_s(self) -> float:
        return self.master_cpu_s + self.worker_cpu_s


IDLE_BETWEEN_S = 0.01  # a rank waits on the network between its segments and comes back to cold caches: a hot
# loop measured 0.015 ms a linreg segment here where the job's ranks measured 0.1 ms (iterations of ~20 ms); with
# 10 ms between iterations the bench measures 0.10 ms (master) and 0.10 ms (worker), as the job does


def bench(options, workers: int, seconds: float) -> BenchResult:
    """CPU seconds per iteration of the job's own work on this machine: the master's input and combine, and one
    worker's work on its block of `workers` equal blocks, repeated for about `seconds` with a pause between
    iterations as the job has (no MPI, no network)."""
    from nac_onboard.compute import kernels

    master, worker = options.task_class(options), options.task_class(options)
    bounds = kernels.split_rows(master.rows(), [1.0] * workers)
    for task in (master, worker):
        task.split(bounds)
    worker.take_block(1)
    master_s = worker_s = 0.0
    iterations = 0
    end = time.monotonic() + seconds
    while iterations < 3 or time.monotonic() < end:
        t0 = time.process_time()
        payload = master.next_input(iterations)
        t1 = time.process_time()
        answer = worker.work(payload)
        t2 = time.process_time()
        master.combine(iterations, payload, {rank: answer for rank in range(1, workers + 1)})
        t3 = time.process_time()
        master_s += (t1 - t0) + (t3 - t2)
        worker_s += t2 - t1
        iterations += 1
        time.sleep(IDLE_BETWEEN_S)
    return BenchResult(master.name, workers, iterations, master_s / iterations, worker_s / iterations)
