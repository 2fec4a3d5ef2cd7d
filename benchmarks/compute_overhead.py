"""Iterations per second of `nac-onboard compute --task linreg --emulate none` with 2 and 4 workers on this
machine, against a bare mpi4py loop that sends the same messages (the same header + weights down, the same
header + gradient up, blocking Send/Recv, no records, no timeouts), in the same run, alternating.
Targets: ratio >= 0.8, and >= 1000 iterations/s with 2 workers. Both programs are launched as the experiment
runner launches jobs (`nac_onboard.compute.launch`: a hydra proxy per rank, each rank pinned as `core_binding`
says: with more ranks than cores, the master alone on core 0).

    python benchmarks/compute_overhead.py [--iterations 3000] [--repeats 11] [--workers 2 4] [--smoke]
    (with --bare-loop, this file is the bare loop itself, run by mpiexec)
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from nac_onboard.compute import launch
from nac_onboard.records import kinds

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

ROOT = Path(__file__).resolve().parents[1]
SMOKE = {"iterations": 200, "repeats": 1, "workers": [2]}  # --smoke: one pair with 2 workers


def bare_loop(iterations: int) -> None:
    import numpy as np
    from mpi4py import MPI

    from nac_onboard.compute import forestfires, kernels

    comm = MPI.COMM_WORLD
    rank, workers = comm.Get_rank(), comm.Get_size() - 1
    x, y = forestfires.load(forestfires.find_csv())
    bounds = kernels.split_rows(len(y), [1.0] * workers)
    d = x.shape[1]
    if rank == 0:
        w = np.zeros(d)
        answer = np.empty(5 + d)
        t0 = time.perf_counter()
        for it in range(iterations):
            message = np.concatenate([[1.0, it, 0.0, 0.0], w])
            for r in range(1, workers + 1):
                comm.Send([message, MPI.DOUBLE], dest=r, tag=1)
            parts = []
            for r in range(1, workers + 1):
                comm.Recv([answer, MPI.DOUBLE], source=r, tag=2)
                parts.append((answer[5:].copy(), float(answer[4]), int(answer[3])))
            gradient, _, _ = kernels.combine_gradients(parts)
            w = w - 0.05 * gradient
        print(json.dumps({"iterations_per_s": iterations / (time.perf_counter() - t0)}))
        for r in range(1, workers + 1):
            comm.Send([np.array([3.0, 0, 0, 0]), MPI.DOUBLE], dest=r, tag=1)
    else:
        start, stop = bounds[rank - 1]
        xs, ys = x[start:stop], y[start:stop]
        message = np.empty(4 + d)
        while True:
            comm.Recv([message, MPI.DOUBLE], source=0, tag=1)
            if message[0] == 3.0:
                break
            gradient, sse, rows = kernels.local_gradient(xs, ys, message[4:])
            comm.Send([np.concatenate([[message[1], 0.0, 0.0, rows, sse], gradient]), MPI.DOUBLE], dest=0, tag=2)


def run(ranks: int, args: list[str], env: dict, finished: Callable[[subprocess.CompletedProcess], object]):
    """The job's answer, `finished(result)`. As the experiment runner does, a job that gave its answer counts even
    when mpiexec exits non-zero after it (hydra with a proxy per rank can die of SIGPIPE in its teardown on a
    loaded machine); without an answer, the exit status and hydra's words end the benchmark."""
    with tempfile.TemporaryDirectory() as config:
        hosts = ["m", *(f"w{k}" for k in range(1, ranks))]
        command = [*launch.mpiexec_command(hosts, Path(config)), sys.executable, "-m", "mpi4py", *args]
        result = subprocess.run(command, capture_output=True, text=True, timeout=600, env=env, cwd=ROOT)
    try:
        answer = finished(result)
    except (ValueError, KeyError, IndexError, TypeError, ZeroDivisionError, OSError):
        answer = None
    if answer is None:
        raise SystemExit(f"{' '.join(command)} exited {result.returncode} without its answer: {result.stderr}")
    if result.returncode != 0:
        print(f"note: mpiexec exited {result.returncode} after the job finished", file=sys.stderr)
    return answer


def measure(workers: int, iterations: int, env: dict) -> tuple[float, float]:
    bare = run(workers + 1, [__file__, "--bare-loop", "--iterations", str(iterations)], env,
               lambda result: json.loads(result.stdout.strip().splitlines()[-1])["iterations_per_s"])
    with tempfile.TemporaryDirectory() as out:
        ours = run(workers + 1, ["-m", "nac_onboard.compute", "--task", "linreg", "--iterations", str(iterations),
                                 "--out", out], env, lambda _: iterations_per_s(Path(out, kinds.COMPUTE_LOG.name)))
    return ours, bare


def iterations_per_s(records: Path) -> float:
    """From the master's summary, the last record of its compute.jsonl."""
    summary = json.loads(records.read_text().splitlines()[-1])
    return summary["iterations"] / summary["elapsed_s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=11)
    parser.add_argument("--workers", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--bare-loop", action="store_true")
    args = _common.parse_args(parser, SMOKE)
    if args.bare_loop:
        bare_loop(args.iterations)
        return
    env = dict(os.environ)
    env.setdefault("NAC_DATA_DIR", str(ROOT.parent / "shared" / "data"))
    for workers in args.workers:
        ours, bare = zip(*(measure(workers, args.iterations, env) for _ in range(args.repeats)), strict=True)
        ratios = [o / b for o, b in zip(ours, bare, strict=True)]
        low, mid, high = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else (ratios[0],) * 3
        print(f"{workers} workers: nac compute {statistics.median(ours):7.0f} it/s, bare mpi4py loop "
              f"{statistics.median(bare):7.0f} it/s, ratio {statistics.median(ratios):.2f} (median of "
              f"{args.repeats} alternating pairs; quartiles {low:.2f}-{high:.2f})")


if __name__ == "__main__":
    main()
