"""`make demo`: the research's flight test in SITL, moving then static, and the comparison of the two; `make
coded-demo` (`--pair coded`): the same straggler flight with the uncoded and the gradient-coded task (issue 30).

    python -m sitl.experiment.demo [--pair research|coded] [--speedup X] [--out runs/demo-ID] [--base-port 14550]

Each scenario is a full `nac-sitl experiment` (simulator, one agent per vehicle, missions, MPI job, report);
the comparison's report.md (RUN/report.md) checks the research's findings against the two runs' numbers.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

from nac_onboard.records import kinds
from sitl.experiment.runner import Outcome, run_scenario
from sitl.experiment.scenario import ScenarioError, load_scenario

SCENARIOS = ("paper-flight-moving", "paper-flight-static")
PAIRS = {"research": SCENARIOS, "coded": ("uncoded-edge", "coded-edge")}  # make demo, make coded-demo


def run_demo(out: Path, speedup: float | None, base_port: int, stream=None,
             stop: threading.Event | None = None, pair: str = "research") -> int:
    stream = sys.stdout if stream is None else stream  # the stdout of now, not of import time
    scenarios = [load_scenario(name) for name in PAIRS[pair]]
    results = []
    for scenario in scenarios:
        print(f"\n=== {scenario.name}: {scenario.description}", file=stream, flush=True)
        pace = min(scenario.default_speedup if speedup is None else speedup, scenario.max_speedup)
        result = run_scenario(scenario, out / scenario.name, pace, base_port, stream, stop)
        results.append(result)
        if result.outcome is Outcome.INTERRUPTED:
            break
    if len(results) == len(scenarios) and all(r.report for r in results):
        from ground.logs.findings import beside_the_research, coded_vs_uncoded, research_findings
        from ground.logs.report import compare_runs

        findings, beside = (research_findings, beside_the_research) if pair == "research" else (coded_vs_uncoded,
                                                                                                None)
        comparison = compare_runs(results[0].run_dir, results[1].run_dir, out / "comparison",
                                  report_path=kinds.REPORT.at(out), findings=findings, beside=beside)
        print(f"\ncomparison: {comparison.report_path}", file=stream)
        for line in comparison.findings:
            print(f"- {line}", file=stream)
    failed = [r for r in results if r.outcome is not Outcome.COMPLETED]
    return failed[0].outcome.exit_code if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sitl.experiment.demo", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--speedup", type=float, default=None,
                        help="every scenario's (default: each its own default_speedup), capped by its max_speedup")
    parser.add_argument("--out", type=Path, default=Path("runs") / f"demo-{time.strftime('%Y%m%dT%H%M%S')}")
    parser.add_argument("--base-port", type=int, default=14550)
    parser.add_argument("--pair", choices=list(PAIRS), default="research",
                        help="research: the flight test moving and static (make demo); coded: the same flight with "
                             "the uncoded and the gradient-coded linear regression (make coded-demo)")
    args = parser.parse_args(argv)
    try:
        return run_demo(args.out, args.speedup, args.base_port, pair=args.pair)
    except ScenarioError as err:
        print(f"python -m sitl.experiment.demo: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
