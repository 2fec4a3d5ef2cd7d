"""What the benchmarks share: the `--smoke` flag every one has (the same code path with tiny sizes, so the test
suite runs them all), and a process's CPU time and memory from /proc."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")


def parse_args(parser: argparse.ArgumentParser, smoke_defaults: dict) -> argparse.Namespace:
    """parser's arguments; with --smoke, smoke_defaults replace the defaults (explicit flags still win)."""
    parser.add_argument("--smoke", action="store_true", help=f"tiny run to check the benchmark works: {smoke_defaults}")
    if parser.parse_known_args()[0].smoke:
        parser.set_defaults(**smoke_defaults)
    return parser.parse_args()


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) the process has used."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def memory_mb(pid: int) -> dict:
    """VmRSS (now) and VmHWM (peak), MB."""
    status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    return {key: int(status[key].split()[0]) / 1024 for key in ("VmRSS", "VmHWM")}
