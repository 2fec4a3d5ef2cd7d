"""The web view's server: what following a live run costs it, and how fast a long run's replay is ready.

- live: 16 vehicles logging telemetry at 10 records/s each into their agent.jsonl (plus the master's probes at
  2/s and an iteration a second), written here for --seconds; `nac-ground view RUN --follow` serves it in its own
  process, pinned to core 0, and one client reads the Server-Sent Events stream throughout. Reported: the
  server's CPU time over the window as a share of one core (target: under 5 %), and how far behind the files
  the stream ran.
- replay: a 10-minute run of the same fleet (96,000 telemetry records and the rest), from starting
  `nac-ground view RUN` to having /api/state and every record through /api/records (target: under 2 s); and,
  with Debian's Chromium and chromedriver here, from the command to the page loaded and drawn.

    python benchmarks/view_server.py [--vehicles 16] [--seconds 30] [--replay-minutes 10] [--smoke]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

from missions.geo import Home, enu_to_lla
from nac_onboard.records import kinds

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SMOKE = {"vehicles": 3, "seconds": 2.0, "replay_minutes": 0.2}
ORIGIN = Home(47.397742, 8.545594, 488.0)
NAC_GROUND = str(Path(sys.executable).parent / "nac-ground")


def telemetry(vehicle: int, t_s: float, t_rel_s: float) -> str:
    angle = t_rel_s * 0.1 + vehicle
    east, north = 40 * math.cos(angle) + vehicle * 5, 40 * math.sin(angle)
    lat, lon, alt = enu_to_lla([east, north, 10.0], ORIGIN)
    return json.dumps({"t_s": t_s, "kind": kinds.TELEMETRY.name, "sysid": vehicle + 1,
                       "time_boot_ms": int(t_rel_s * 1000),
                       "lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt), "rel_alt_m": 10.0,
                       "vel_ned_mps": [1.0, 0.5, 0.0], "roll_deg": 0.5, "pitch_deg": -1.0, "yaw_deg": 45.0,
                       "battery_pct": 80, "voltage_v": 15.9, "mode": "AUTO", "armed": True, "landed": 2,
                       "mission_seq": 3, "mission_total": 6}) + "\n"


def probe(t_s: float, worker: int, bps: float) -> str:
    return json.dumps({"t_s": t_s, "kind": kinds.THROUGHPUT.name, "client": "v00", "server": f"v{worker:02d}",
                       "distance_m": 30.0, "end": {"sum_received": {"bits_per_second": bps}}}) + "\n"


def iteration(t_s: float, k: int, workers: int) -> str:
    return json.dumps({"t_s": t_s, "kind": kinds.ITERATION.name, "iteration": k, "duration_s": 0.8,
                       "cost": 100 / (k + 1),
                       "workers": {"present": [True] * workers}}) + "\n"


def open_logs(run: Path, vehicles: int, stack: contextlib.ExitStack) -> dict:
    files = {}
    for v in range(vehicles):
        folder = run / f"v{v:02d}"
        folder.mkdir(parents=True, exist_ok=True)
        files[v] = stack.enter_context(open(folder / kinds.AGENT_LOG.name, "a"))  # noqa: SIM115 (the stack closes it)
        files[v].write(json.dumps({"t_s": time.time(), "kind": kinds.AGENT_STARTED.name, "role":
                                   "master" if v == 0 else "worker"}) + "\n")
    kinds.COMPUTE_LOG.at(run).parent.mkdir(exist_ok=True)
    files["probes"] = stack.enter_context(open(kinds.THROUGHPUT_LOG.at(run, "v00"), "a"))  # noqa: SIM115
    files["compute"] = stack.enter_context(open(kinds.COMPUTE_LOG.at(run), "a"))  # noqa: SIM115
    return files


def start_view(run: Path, *extra: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([NAC_GROUND, "view", str(run), "--address", "127.0.0.1:0", *extra],
                            stdout=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    if not line.startswith("view: http"):
        proc.kill()
        raise RuntimeError(f"nac-ground view did not start: {line!r}")
    return proc, line.split()[1]


def records_in(frames: list[dict]) -> int:
    """Records the frames hold: a "pos" frame is a batch of positions, as columns."""
    return sum(len(f["t"]) if f["k"] == "pos" else 1 for f in frames)


def live(vehicles: int, seconds: float, folder: Path) -> dict:
    with contextlib.ExitStack() as stack:
        return _live(folder / "live", vehicles, seconds, open_logs(folder / "live", vehicles, stack))


def _live(run: Path, vehicles: int, seconds: float, files: dict) -> dict:
    proc, url = start_view(run, "--follow")
    os.sched_setaffinity(proc.pid, {0})
    received, lag_s = [0], []

    def client():
        with urllib.request.urlopen(url + "api/stream?after=-1", timeout=seconds + 30) as stream:
            for raw in stream:
                if raw.startswith(b"data: ["):
                    batch = json.loads(raw[6:])
                    received[0] += records_in(batch)
                    newest = max(max(f["t"]) if f["k"] == "pos" else f["t"] for f in batch)
                    lag_s.append(time.time() - newest)

    threading.Thread(target=client, daemon=True).start()
    t_start = time.time()
    cpu0, wall0 = _common.cpu_s(proc.pid), time.monotonic()
    written, k = 0, 0
    next_s = time.monotonic()
    while time.monotonic() - wall0 < seconds:
        now = time.time()
        for v in range(vehicles):
            files[v].write(telemetry(v, now, now - t_start))
            files[v].flush()
        written += vehicles
        if k % 5 == 0:
            for w in range(1, vehicles):
                files["probes"].write(probe(now, w, 2e7))
            files["probes"].flush()
            written += vehicles - 1
        if k % 10 == 0:
            files["compute"].write(iteration(now, k // 10, vehicles - 1))
            files["compute"].flush()
            written += 1
        k += 1
        next_s += 0.1
        time.sleep(max(next_s - time.monotonic(), 0.0))
    time.sleep(0.5)  # the last batch's poll
    cpu = _common.cpu_s(proc.pid) - cpu0
    wall = time.monotonic() - wall0
    proc.terminate()
    proc.wait(10)
    return {"cpu_pct": 100 * cpu / wall, "written": written + vehicles, "received": received[0],
            "lag_p50_s": sorted(lag_s)[len(lag_s) // 2] if lag_s else None}


def replay(vehicles: int, minutes: float, folder: Path) -> dict:
    run = folder / "replay"
    t0 = time.time() - minutes * 60
    with contextlib.ExitStack() as stack:
        files = open_logs(run, vehicles, stack)
        for k in range(int(minutes * 60 * 10)):
            t = t0 + k * 0.1
            for v in range(vehicles):
                files[v].write(telemetry(v, t, k * 0.1))
            if k % 5 == 0:
                for w in range(1, vehicles):
                    files["probes"].write(probe(t, w, 2e7))
            if k % 10 == 0:
                files["compute"].write(iteration(t, k // 10, vehicles - 1))
    size_mb = sum(p.stat().st_size for p in run.rglob("*.jsonl")) / 1e6
    browser = headless_browser(folder)
    if browser is not None:
        browser.get("about:blank")  # Chromium done starting before the clock runs
    try:
        start = time.monotonic()
        proc, url = start_view(run)
        try:
            state = json.loads(urllib.request.urlopen(url + "api/state", timeout=30).read())
            body = urllib.request.urlopen(url + "api/records", timeout=30).read()
            ready_s = time.monotonic() - start  # every byte here; parsing them is the client's time
            records = json.loads(body)
        finally:
            proc.terminate()
            proc.wait(10)
        page_s = None
        if browser is not None:  # end to end: from the command to the page drawn with every record
            start = time.monotonic()
            proc, url = start_view(run)
            try:
                browser.get(url)
                while not browser.execute_script("return document.body.dataset.ready"):
                    time.sleep(0.01)
                page_s = time.monotonic() - start
            finally:
                proc.terminate()
                proc.wait(10)
    finally:
        if browser is not None:
            browser.quit()
    return {"ready_s": ready_s, "page_s": page_s, "records": records_in(records), "state_records": state["records"],
            "mb": size_mb}


def headless_browser(folder: Path):
    """Debian's Chromium through its chromedriver, when both (and selenium) are here; else None."""
    import shutil

    from ground.view.serve import CHROMIUM_FLAGS, chromium

    if not (chromium() and shutil.which("chromedriver")):
        return None
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        return None
    options = webdriver.ChromeOptions()
    options.binary_location = chromium()
    for flag in [*CHROMIUM_FLAGS, f"--user-data-dir={folder / 'profile'}"]:
        options.add_argument(flag)
    return webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, default=16)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--replay-minutes", type=float, default=10.0)
    args = _common.parse_args(parser, SMOKE)
    os.sched_setaffinity(0, {1 % os.cpu_count()})
    with tempfile.TemporaryDirectory() as folder:
        r = live(args.vehicles, args.seconds, Path(folder))
        print(f"live: {args.vehicles} vehicles at 10 telemetry records/s for {args.seconds:g} s: server "
              f"{r['cpu_pct']:.1f} % of a core; {r['received']} of {r['written']} records streamed, median lag "
              f"{r['lag_p50_s'] if r['lag_p50_s'] is None else round(r['lag_p50_s'], 3)} s", flush=True)
        r = replay(args.vehicles, args.replay_minutes, Path(folder))
        page = "no browser here" if r["page_s"] is None else f"{r['page_s']:.2f} s"
        print(f"replay: {args.replay_minutes:g} min of {args.vehicles} vehicles ({r['records']} records, "
              f"{r['mb']:.1f} MB of logs): server started and every record served in {r['ready_s']:.2f} s; from "
              f"the command to the page drawn in headless Chromium: {page}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
