"""`make demo`: the research's flight test in SITL, moving then static, and the comparison of the two.

    python -m sitl.experiment.demo [--speedup 1] [--out runs/demo-ID] [--base-port 14550]

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


def run_demo(out: Path, speedup: float, base_port: int, stream=None,
             stop: threading.Event | None = None) -> int:
    stream = sys.stdout if stream is None else stream  # the stdout of now, not of import time
    scenarios = [load_scenario(name) for name in SCENARIOS]
    speedup = min([speedup, *(s.max_speedup for s in scenarios)])
    results = []
    for scenario in scenarios:
        print(f"\n=== {scenario.name}: {scenario.description}", file=stream, flush=True)
        result = run_scenario(scenario, out / scenario.name, speedup, base_port, stream, stop)
        results.append(result)
        if result.outcome is Outcome.INTERRUPTED:
            break
    if len(results) == len(scenarios) and all(r.report for r in results):
        from ground.logs.findings import beside_the_research, research_findings
        from ground.logs.report import compare_runs

        comparison = compare_runs(results[0].run_dir, results[1].run_dir, out / "comparison",
                                  report_path=kinds.REPORT.at(out), findings=research_findings,
                                  beside=beside_the_research)
        print(f"\ncomparison: {comparison.report_path}", file=stream)
        for line in comparison.findings:
            print(f"- {line}", file=stream)
    failed = [r for r in results if r.outcome is not Outcome.COMPLETED]
    return failed[0].outcome.exit_code if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sitl.experiment.demo", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--speedup", type=float, default=1.0, help="capped by each scenario's max_speedup")
    parser.add_argument("--out", type=Path, default=Path("runs") / f"demo-{time.strftime('%Y%m%dT%H%M%S')}")
    parser.add_argument("--base-port", type=int, default=14550)
    args = parser.parse_args(argv)
    try:
        return run_demo(args.out, args.speedup, args.base_port)
    except ScenarioError as err:
        print(f"python -m sitl.experiment.demo: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
