"""Every benchmark still runs: each `benchmarks/*.py` (found by glob, so a new one is covered without editing this
file) with `--smoke`, the same code path at tiny sizes, must exit 0 and print its figures."""

import subprocess
import sys

import pytest

from tests.conftest import REPO

BENCHMARKS = sorted(p for p in (REPO / "benchmarks").glob("*.py") if not p.name.startswith("_"))  # _: helpers
TIMEOUT_S = 120


def test_benchmarks_are_found():
    assert BENCHMARKS, f"no benchmarks under {REPO / 'benchmarks'}"


@pytest.mark.parametrize("path", BENCHMARKS, ids=[p.stem for p in BENCHMARKS])
def test_benchmark_smoke_run(path):
    try:
        result = subprocess.run([sys.executable, str(path), "--smoke"], cwd=REPO, capture_output=True, text=True,
                                timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired as err:
        pytest.fail(f"{path.name} --smoke ran over {TIMEOUT_S} s; stdout so far: {err.stdout!r}")
    detail = f"{path.name} --smoke exited {result.returncode}\nstdout:\n{result.stdout[-3000:]}\n" \
             f"stderr:\n{result.stderr[-3000:]}"
    assert result.returncode == 0, detail
    assert result.stdout.strip(), detail
