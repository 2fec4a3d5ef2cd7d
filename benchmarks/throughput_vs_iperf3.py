"""Our throughput probe against iperf3 on plain loopback, where no link limits either tool and both are bound by
the CPU: how close the Python probe comes to the C tool. Alternating runs, servers pinned to CPU 0 and clients
to CPU 1, the same write size (1 MiB) for both; the test suite compares them on shaped paths instead.

    python benchmarks/throughput_vs_iperf3.py [--runs 21] [--gib 1] [--smoke]
"""

from __future__ import annotations

import argparse
import statistics
import sys

from nac_onboard.link import iperf3

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SMOKE = {"runs": 2, "gib": 4 / 1024}  # --smoke: two pairs of 4 MiB runs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=21)
    parser.add_argument("--gib", type=float, default=1.0, help="bytes per run, GiB")
    args = _common.parse_args(parser, SMOKE)
    if not iperf3.available():
        print("iperf3 is not installed: nothing to compare against, skipped")
        return 0
    result = iperf3.compare("127.0.0.1", runs=args.runs, nbytes=int(args.gib * (1 << 30)))
    for name, rates in (("nac probe", result.ours_bps), ("iperf3", result.iperf3_bps)):
        gbps = sorted(r / 1e9 for r in rates)
        print(f"{name:>9}: median {statistics.median(gbps):.1f} Gbit/s, range {gbps[0]:.1f}-{gbps[-1]:.1f} "
              f"over {len(gbps)} runs")
    ratios = sorted(a / b for a, b in zip(result.ours_bps, result.iperf3_bps, strict=True))
    print(f"ours/iperf3 per adjacent pair: median {result.ratio:.3f}, quartiles {ratios[len(ratios) // 4]:.3f}-"
          f"{ratios[3 * len(ratios) // 4]:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
