"""Writes tests/data/golden-run: a small run directory whose numbers are known by construction (see
tests/unit/test_log_analysis.py for the values it must give), through the records module as every writer does
(tests/unit/test_records.py checks the committed files are what this writes):

    NAC_RECORDS_STRICT=1 python tests/data/make_golden_run.py
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from missions.geo import Home, enu_to_lla  # noqa: E402 (after the path above)
from nac_onboard.flight_log import JsonlLog  # noqa: E402
from nac_onboard.records import kinds  # noqa: E402

HOME = Home(47.0, 8.0, 500.0)
OUT = Path(__file__).parent / "golden-run"
T0_S = 999.0  # when every file was opened


def position(east_m: float) -> dict:
    lat, lon, alt = enu_to_lla([east_m, 0.0, 10.0], HOME)
    return {"lat_deg": round(float(lat), 9), "lon_deg": round(float(lon), 9), "alt_m": round(float(alt), 4)}


def telemetry(log: JsonlLog, t_s: float, boot_ms: int, east_m: float) -> None:
    log.write(kinds.TELEMETRY, t_s, sysid=1, time_boot_ms=boot_ms, **position(east_m), rel_alt_m=10.0,
              vel_ned_mps=[0.0, 0.0, 0.0], roll_deg=0.0, pitch_deg=0.0, yaw_deg=0.0, mode="AUTO", armed=True)


def probe(log: JsonlLog, t_s: float, distance_m: float, mbps: float | None) -> None:
    fields = {"client": "master", "server": "w1", "host": "w1", "port": 5201, "t_sim_s": t_s - 1000.0,
              "speedup": 1.0, "positions": {"start": None, "end": None}, "distance_m": distance_m,
              "start": {"timestamp": {"timesecs": t_s}}}
    if mbps is None:
        fields["error"] = "unable to connect to server: timed out"
    else:
        fields["end"] = {"sum_sent": {"retransmits": 0},
                         "sum_received": {"bits_per_second": mbps * 1e6, "bytes": int(mbps * 1e6 / 8), "seconds": 1.0}}
    log.write(kinds.THROUGHPUT, t_s + 1.0, **fields)


def iteration(log: JsonlLog, k: int, start_s: float, duration_s: float, cost: float, w2_absent: str | None) -> None:
    log.write(kinds.ITERATION, start_s + duration_s, iteration=k, start_s=start_s, end_s=start_s + duration_s,
              duration_s=duration_s, complete=True, cost=cost,
              workers={"rank": [1, 2], "vehicle": ["w1", "w2"], "present": [True, w2_absent is None],
                       "absent": [None, w2_absent], "distance_m": [11.9, 25.0], "bytes_down": [248, 248]})


def agent_started(log: JsonlLog, vehicle: str, role: str) -> None:
    log.write(kinds.AGENT_STARTED, T0_S, vehicle=vehicle, role=role, config=f"{vehicle}.toml",
              autopilot="udpin:127.0.0.1:14551", run_dir=vehicle, pid=1, mpi_build=None)


def write_golden(out: Path) -> None:
    with JsonlLog(kinds.AGENT_LOG.at(out, "master"), T0_S) as log:
        agent_started(log, "master", "master")
        for k in range(5):
            telemetry(log, 1000.0 + k, 1000 * k, 0.0)
    with JsonlLog(kinds.AGENT_LOG.at(out, "w1"), T0_S) as log:
        agent_started(log, "w1", "worker")
        # w1 flies east at 2 m/s; its log lags the master's by 0.05 s and logs its first sample twice
        for k, (t_s, boot_ms, east_m) in enumerate([(1000.05 + k, 1000 * k, 10.0 + 2 * k) for k in range(5)]):
            telemetry(log, t_s, boot_ms, east_m)
            if k == 0:
                telemetry(log, 1000.55, 0, 10.0)
    with JsonlLog(kinds.THROUGHPUT_LOG.at(out, "master"), T0_S) as log:
        for t_s, distance_m, mbps in [(1000.0, 3.0, 40.0), (1001.0, 3.5, 60.0), (1002.0, 5.0, 30.0),
                                      (1003.0, 9.0, 10.0), (1004.0, 9.5, 20.0), (1005.0, 21.0, None)]:
            probe(log, t_s, distance_m, mbps)
    with JsonlLog(kinds.COMPUTE_LOG.at(out), T0_S) as log:
        log.write(kinds.RUN_STARTED, 1000.5, warmup_s=0.01, task="linreg", workers=2, shards=[[0, 258], [258, 517]],
                  emulate="positions", pad_bits=0, speedup=1.0, timeout_s=5.0, on_missing="skip",
                  allocation="equal", pid=1)
        for args in [(0, 1001.0, 0.5, 10.0, None), (1, 1001.5, 0.5, 8.0, None), (2, 1002.0, 1.0, 7.0, "out_of_range"),
                     (3, 1003.0, 0.5, 6.5, None)]:
            iteration(log, *args)
        log.write(kinds.RUN_SUMMARY, 1003.6, task="linreg", iterations=4, complete_iterations=4,
                  ended_by="iterations", elapsed_s=2.6, elapsed_sim_s=2.6, mean_duration_s=0.625,
                  p95_duration_s=0.925, absent_iterations={"1": 0, "2": 1}, stale_results=0, lost_workers=[],
                  failed_workers=[], final_cost=6.5)


if __name__ == "__main__":
    import shutil

    shutil.rmtree(OUT, ignore_errors=True)
    write_golden(OUT)
