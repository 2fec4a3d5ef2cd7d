"""The companion's CPU: a device profile, and each rank's work stretched to that device's time on the run's clock.

A rank measures the CPU seconds its own work takes on this host (`time.process_time`: what a loaded host's other
processes take is not counted) and holds the result until `slowdown` times that has passed on the run's clock. So
a job that computes on a Jetson that is 6 times slower than this host takes the Jetson's time in simulated
seconds, at 1x as at any speed-up up to about the slowdown: above that the host's own time is longer than the
device's, the segment comes out late, and the run counts it (`late_cpu_segments`).

The slowdown is the device's CPU time over this host's for the job's work. A profile gives it either as measured
(`slowdown`: `nac-onboard bench` times the task's work here and on the companion) or as the device's single-thread
CPU score (`cpu_score_mips`, 7-Zip's rating by sbc-bench's method), divided into this host's own score
(`nac_onboard.compute.cpu_score`). NAC ships Jetson profiles of the second kind (`devices/`), each with its
published source.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path

import tomllib

from nac_onboard.compute import cpu_score
from nac_onboard.errors import BadInput
from nac_onboard.inputs import MAX_CONFIG_BYTES, check_regular_file

log = logging.getLogger(__name__)

SLOWDOWN_RANGE = (1.0, 1000.0)  # a companion slower than this host (down to a microcontroller's ~1000x); a faster
# one cannot be emulated by holding results back, so 1.0 (no stretch) is the floor


@dataclass(frozen=True)
class DeviceProfile:
    name: str
    slowdown: float  # the device's CPU seconds per CPU second of this host, for the job's work
    source: str  # who measured it, on what, how
    cpu_score_mips: float | None = None  # the device's 7-Zip single-thread rating, where the slowdown comes from it


HOST = DeviceProfile("host", 1.0, "this machine: no stretch")
SHIPPED = Path(__file__).with_name("devices")  # the Jetson profiles NAC ships, by name (jetson-tx2, ...)
FIELDS = ("name", "slowdown", "cpu_score_mips", "source")


def shipped_devices() -> list[str]:
    return sorted(p.stem for p in SHIPPED.glob("*.toml"))


def device_path(value: str | Path, base: Path | None = None) -> Path:
    """A profile named on a command line or in a scenario: a file (relative to base), else a shipped profile's name."""
    path = Path(base or ".") / value
    if not path.exists() and str(value) in shipped_devices():
        return SHIPPED / f"{value}.toml"
    return path


def load_device_profile(path: str | Path, measure_host: bool = False) -> DeviceProfile:
    """A [device] table: name, source (required: a figure without one is not used), and either slowdown (in
    SLOWDOWN_RANGE) or cpu_score_mips (the slowdown is then this host's score over it, measured once per machine if
    measure_host, at least 1). A shipped profile's name is taken for a path that does not exist."""
    named, path = path, device_path(path)
    if not path.exists():  # a mistyped shipped name reads as a missing file: say which names there are
        raise BadInput(f"cannot read device profile {path}: no such file, and {Path(named).name!r} is not a shipped "
                       f"profile's name ({', '.join(shipped_devices())})")
    check_regular_file(path, "device profile", MAX_CONFIG_BYTES)
    try:
        table = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise BadInput(f"{path}: not TOML ({err})") from err
    device = table.get("device")
    if not isinstance(device, dict):
        raise BadInput(f"{path}: expected a [device] table with name, source and slowdown or cpu_score_mips")
    name, source = device.get("name"), device.get("source")
    if not isinstance(name, str) or not name.strip():
        raise BadInput(f"{path}: [device] name: expected a non-empty string")
    if not isinstance(source, str) or not source.strip():
        raise BadInput(f"{path}: [device] source: expected who measured the slowdown, on what and how")
    unknown = sorted(set(device) - set(FIELDS))
    if unknown:
        raise BadInput(f"{path}: [device] has unknown fields {unknown}; expected {', '.join(FIELDS)}")
    if ("slowdown" in device) == ("cpu_score_mips" in device):
        raise BadInput(f"{path}: [device]: expected exactly one of slowdown (measured for this job) and "
                       f"cpu_score_mips (the device's 7-Zip single-thread rating)")
    if "slowdown" in device:
        slowdown = _number(path, "slowdown", device["slowdown"], SLOWDOWN_RANGE,
                           "the device's CPU seconds per CPU second of this host")
        return DeviceProfile(name.strip(), slowdown, source.strip())
    score = _number(path, "cpu_score_mips", device["cpu_score_mips"], cpu_score.CPU_SCORE_RANGE,
                    "7-Zip's single-thread rating in MIPS, sbc-bench's method")
    host = cpu_score.host_cpu_score_mips(measure_if_missing=measure_host)
    if host < score:
        log.info("%s: the device's CPU score %g is above this host's %g: no stretch", path, score, host)
    return DeviceProfile(name.strip(), max(1.0, host / score), source.strip(), score)


def _number(path: Path, field: str, value, bounds: tuple[float, float], meaning: str) -> float:
    low, high = bounds
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) \
            or not low <= value <= high:
        raise BadInput(f"{path}: [device] {field}: expected a number in {low:g}..{high:g} ({meaning}), got {value!r}")
    return float(value)


class CpuStretch:
    """Time one segment of a rank's work (`begin` ... `hold`) as the device would take it on the run's clock."""

    def __init__(self, slowdown: float, clock):
        self.slowdown, self.clock = slowdown, clock
        self.late = 0  # segments whose host time on the run's clock was already longer than the device's
        self.late_s = 0.0  # simulated: by how much, in all (a preempted rank's few ms, or a host too slow for it)
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
            self.late_s += self.clock.sim_s(-remaining_wall_s)
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
