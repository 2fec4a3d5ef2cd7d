"""Writes tests/data/golden-run: a small run directory whose numbers are known by construction (see
tests/unit/test_log_analysis.py for the values it must give). Kept to show how the fixture was made:

    python tests/data/make_golden_run.py
"""

import json
from pathlib import Path

from missions.geo import Home, enu_to_lla

HOME = Home(47.0, 8.0, 500.0)
OUT = Path(__file__).parent / "golden-run"


def position(east_m: float) -> dict:
    lat, lon, alt = enu_to_lla([east_m, 0.0, 10.0], HOME)
    return {"lat_deg": round(float(lat), 9), "lon_deg": round(float(lon), 9), "alt_m": round(float(alt), 4)}


def write(path: Path, records: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def telemetry(t_s: float, boot_ms: int, east_m: float) -> dict:
    return {"t_s": t_s, "kind": "telemetry", "sysid": 1, "time_boot_ms": boot_ms, **position(east_m), "armed": True}


def probe(t_s: float, distance_m: float, mbps: float | None) -> dict:
    record = {"t_s": t_s + 1.0, "kind": "throughput", "client": "master", "server": "w1", "distance_m": distance_m,
              "start": {"timestamp": {"timesecs": t_s}}}
    if mbps is None:
        record["error"] = "unable to connect to server: timed out"
    else:
        record["end"] = {"sum_sent": {"retransmits": 0},
                         "sum_received": {"bits_per_second": mbps * 1e6, "bytes": int(mbps * 1e6 / 8), "seconds": 1.0}}
    return record


def iteration(k: int, start_s: float, duration_s: float, cost: float, w2_absent: str | None) -> dict:
    return {"t_s": start_s + duration_s, "kind": "iteration", "iteration": k, "start_s": start_s,
            "end_s": start_s + duration_s, "duration_s": duration_s, "complete": True, "cost": cost,
            "workers": {"rank": [1, 2], "vehicle": ["w1", "w2"], "present": [True, w2_absent is None],
                        "absent": [None, w2_absent], "distance_m": [11.9, 25.0], "bytes_down": [248, 248]}}


write(OUT / "master" / "agent.jsonl", [{"t_s": 999.0, "kind": "agent_started", "vehicle": "master", "role": "master"}]
      + [telemetry(1000.0 + k, 1000 * k, 0.0) for k in range(5)])
# w1 flies east at 2 m/s; its log lags the master's by 0.05 s and logs its first sample twice
w1 = [telemetry(1000.05 + k, 1000 * k, 10.0 + 2 * k) for k in range(5)]
w1.insert(1, telemetry(1000.55, 0, 10.0))
write(OUT / "w1" / "agent.jsonl", [{"t_s": 999.0, "kind": "agent_started", "vehicle": "w1", "role": "worker"}] + w1)
write(OUT / "master" / "throughput.jsonl", [probe(1000.0, 3.0, 40.0), probe(1001.0, 3.5, 60.0),
                                            probe(1002.0, 5.0, 30.0), probe(1003.0, 9.0, 10.0),
                                            probe(1004.0, 9.5, 20.0), probe(1005.0, 21.0, None)])
write(OUT / "compute" / "compute.jsonl",
      [{"t_s": 1000.5, "kind": "run_started", "task": "linreg", "workers": 2}]
      + [iteration(0, 1001.0, 0.5, 10.0, None), iteration(1, 1001.5, 0.5, 8.0, None),
         iteration(2, 1002.0, 1.0, 7.0, "out_of_range"), iteration(3, 1003.0, 0.5, 6.5, None)]
      + [{"t_s": 1003.6, "kind": "run_summary", "iterations": 4}])
