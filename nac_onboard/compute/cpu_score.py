"""This machine's single-thread CPU score, the figure a device profile's `cpu_score_mips` is compared against.

The score is 7-Zip's benchmark rating with one thread (`7z b -mmt1`, dictionaries 2^22..2^25: the "Tot" MIPS), pinned
to one core: the method of sbc-bench (Thomas Kaiser), whose published results give the Jetsons' figures. 7-Zip's
LZMA is branchy integer code bound by cache and memory latency, as CPython's interpreter loop, pickling and an MPI
library's per-message path are; it does not measure vector floating point (numpy's kernels), which is a small part
of this job's CPU (docs/compute.md). Measuring takes about 50 s, so the figure is kept per machine in the user's
cache for this CPU model (with the 7-Zip build it was measured with); $NAC_HOST_CPU_SCORE overrides it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shutil
import subprocess
import time
from pathlib import Path

from nac_onboard.errors import BadInput, OperationFailed

log = logging.getLogger(__name__)

HOST_CPU_SCORE_ENV = "NAC_HOST_CPU_SCORE"
CPU_SCORE_RANGE = (100.0, 100_000.0)  # MIPS: sbc-bench's slowest boards rate ~500, a desktop core ~6,000
MEASURE_TIMEOUT_S = 600.0  # 50 s on this 2-core VM; a slow board or a loaded host takes longer
_TOT = re.compile(r"^Tot:\s+\d+\s+\d+\s+(\d+)\s*$", re.MULTILINE)


def parse_rating(text: str) -> float:
    """The overall rating (MIPS) from `7z b` output: the last field of its "Tot:" line."""
    found = _TOT.findall(text)
    if not found:
        raise OperationFailed("7z b printed no 'Tot:' line with a rating")
    return float(found[-1])


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.split(":")[0].strip() in ("model name", "Model", "Hardware"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return os.uname().machine


def _cache_path() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "nac" / "host-cpu-score.json"


def measure() -> tuple[float, str]:
    """Run the benchmark now on one core: (rating in MIPS, the 7-Zip build's first line)."""
    sevenzip = shutil.which("7z") or shutil.which("7za") or shutil.which("7zr")
    if sevenzip is None:
        raise OperationFailed("no 7z: install p7zip-full (apt-get install p7zip-full) to measure this host's CPU score")
    pin = ["taskset", "-c", str(max(os.sched_getaffinity(0)))] if shutil.which("taskset") else []
    command = [*pin, sevenzip, "b", "-mmt1"]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=MEASURE_TIMEOUT_S, check=False)
    except subprocess.TimeoutExpired:
        raise OperationFailed(f"7z b took over {MEASURE_TIMEOUT_S:g} s") from None
    if done.returncode != 0:
        raise OperationFailed(f"7z b exited {done.returncode}: {done.stderr.strip()[-300:]}")
    build = next((line.strip() for line in done.stdout.splitlines() if line.startswith("7-Zip")), "7-Zip")
    return parse_rating(done.stdout), build


def host_cpu_score_mips(measure_if_missing: bool = False) -> float:
    """This machine's score: $NAC_HOST_CPU_SCORE, else the cached measurement for this CPU, else (if allowed)
    measured now and cached. Without one, BadInput naming the command that measures it."""
    low, high = CPU_SCORE_RANGE
    if os.environ.get(HOST_CPU_SCORE_ENV):
        text = os.environ[HOST_CPU_SCORE_ENV]
        try:
            score = float(text)
        except ValueError:
            score = math.nan
        if not (math.isfinite(score) and low <= score <= high):
            raise BadInput(f"${HOST_CPU_SCORE_ENV}: expected 7-Zip's single-thread rating in {low:g}..{high:g} "
                           f"MIPS, got {text!r}")
        return score
    cached = _cached()
    if cached is not None:
        return cached
    if not measure_if_missing:
        raise BadInput(f"this host's CPU score is not measured yet (a device profile with cpu_score_mips needs it): "
                       f"run `nac-onboard cpu-score` once (about a minute), or set ${HOST_CPU_SCORE_ENV}")
    return measure_and_cache()


def measure_and_cache() -> float:
    log.info("measuring this host's single-thread CPU score once (7z b -mmt1, about a minute)")
    score, build = measure()
    path = _cache_path()
    record = {"cpu": _cpu_model(), "build": build, "score_mips": score, "measured_unix_s": time.time()}
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(record) + "\n")
        tmp.replace(path)
    except OSError as err:
        log.warning("could not keep the CPU score in %s: %s", path, err)
    return score


def _cached() -> float | None:
    """The cached score if it was measured on this CPU model; a damaged or foreign file is measured again."""
    path = _cache_path()
    try:
        record = json.loads(path.read_text())
        score = float(record["score_mips"])
        cpu = record["cpu"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    low, high = CPU_SCORE_RANGE
    if cpu != _cpu_model() or not (math.isfinite(score) and low <= score <= high):
        return None
    return score
