"""The web view in a real browser: Debian's headless Chromium driven through chromedriver by selenium. The live
page of a short SITL experiment against the simulator's truth, then the finished run replayed and scrubbed."""

import json
import shutil
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from ground.view.records import RunFollower, positions
from ground.view.serve import ViewThread, screenshot
from ground.view.server import ViewServer
from missions import save_mission
from missions.builder import Builder
from missions.geo import Home, enu_to_lla, lla_to_enu
from sitl.experiment.runner import Experiment, Outcome, save_screenshot
from sitl.experiment.scenario import load_scenario
from sitl.scenarios.generate import at, hover
from tests.conftest import allocate_base_port
from tests.integration.conftest import needs_browser
from tests.integration.test_experiment import write_scenario

pytestmark = needs_browser
VEHICLES_JS = """return [...document.querySelectorAll('#vehicles .vehicle')].map(g => ({
    id: g.dataset.id, e: +g.dataset.e, n: +g.dataset.n, t: +g.dataset.t, tb: +g.dataset.tb}));"""


def wait_for(browser, script: str, timeout_s: float = 20.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = browser.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"the page never answered {script!r} within {timeout_s} s")


def scrub(browser, offset_s: float) -> None:
    """Move the timeline's slider to offset_s as a user's drag does (its input event)."""
    browser.execute_script("const s = document.getElementById('cursor'); s.value = arguments[0];"
                           "s.dispatchEvent(new Event('input'));", offset_s)


def out_and_back_scenario(folder: Path) -> Path:
    """write_scenario's fleet, but w1 holds 10 s where it took off (the probes begin at the run's go, once all are
    up: 1 s of wall time in range at 10x), then flies 120 m out (the channel's median range is 47 m) and back at
    12 m/s."""
    path = write_scenario(folder, duration_s=55.0)
    w1 = Builder(at(5, 0)).takeoff(5.0).hold(0.0, 0.0, 5.0, 10.0).speed(12.0).waypoint(120.0, 0.0, 5.0) \
        .waypoint(5.0, 0.0, 5.0).hold(5.0, 0.0, 5.0, 60.0).land(5.0, 0.0).mission()
    save_mission(w1, folder / "w1.plan")
    save_mission(hover(at(0, 0), 5.0), folder / "master.plan")
    return path


@pytest.mark.slow
@pytest.mark.exclusive  # a 10x SITL run followed live: on a busy core its first frames come late
def test_the_live_page_follows_the_simulator_and_the_replay_scrubs_through_the_records(browser, tmp_path):
    scenario = load_scenario(str(out_and_back_scenario(tmp_path / "scenario")))
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    truth_t, truth_pos = [], []
    console = (tmp_path / "console.txt").open("w")  # closed with the experiment, below
    experiment = Experiment(scenario, run_dir, 10.0, allocate_base_port(3, slots=5), out=console, analyze=False)
    experiment.step_observers.append(lambda t, state: (truth_t.append(t), truth_pos.append(state.pos_m.copy())))
    viewer = ViewThread(ViewServer(run_dir, live=True), "127.0.0.1:0")
    result = []
    runner = threading.Thread(target=lambda: result.append(experiment.run()), daemon=True)
    url = viewer.start()
    runner.start()
    homes = [Home(v.home.lat_deg, v.home.lon_deg, v.home.alt_m) for v in scenario.vehicles]
    ids = [v.id for v in scenario.vehicles]
    errors_m, link_states, iterations = [], [], []
    try:
        browser.get(url)
        wait_for(browser, "return document.body.dataset.ready && "
                          "document.querySelectorAll('#vehicles .vehicle').length === 3", 60.0)
        origin = wait_for(browser, "return window.nacView.info.origin")  # known once a position is heard
        origin = Home(origin["lat_deg"], origin["lon_deg"], origin["alt_m"])
        while runner.is_alive():
            times = np.array(truth_t)
            for v in browser.execute_script(VEHICLES_JS):
                k = int(np.argmin(np.abs(times - v["tb"])))
                if abs(times[k] - v["tb"]) > 0.05:
                    continue
                lat, lon, alt = enu_to_lla(truth_pos[k][ids.index(v["id"])], homes[ids.index(v["id"])])
                true_m = lla_to_enu(float(lat), float(lon), float(alt), origin)
                errors_m.append(float(np.hypot(v["e"] - true_m[0], v["n"] - true_m[1])))
            link_states.append(browser.execute_script(
                "const l = document.querySelector('#links line[data-worker=w1]'); return l && l.dataset.state"))
            iterations.append(int(browser.execute_script(
                "const i = document.getElementById('iterations'); return i ? +i.dataset.count : 0")))
            time.sleep(0.3)
        runner.join(120)
        save_screenshot(viewer, run_dir, console)  # what `--view` does when the run ends
    finally:
        experiment.stop_event.set()
        runner.join(120)
        viewer.stop()
        console.close()
    assert result and result[0].outcome is Outcome.COMPLETED, result
    assert len(errors_m) > 30 and max(errors_m) < 1.0, f"drawn up to {max(errors_m):.2f} m from the truth"
    states = [s for k, s in enumerate(link_states) if s and (k == 0 or s != link_states[k - 1])]
    assert states[:3] == ["up", "out", "up"], f"w1's link over time: {states}"
    # counted while watched: from the first iteration shown (on a loaded machine the job can start a quarter of the
    # way into this 10x run: a CI run saw 0 there) to a larger count by the end
    shown = [count for count in iterations if count > 0]
    assert shown and shown[-1] > shown[0], f"the iteration counter advanced: {iterations}"
    shot = (run_dir / "view.png").read_bytes()
    assert shot[:8] == b"\x89PNG\r\n\x1a\n" and len(shot) > 20_000, "the live page's screenshot"

    # The finished run, replayed: the slider scrubbed to three times, each vehicle where its records say.
    follower = RunFollower(run_dir)
    follower.poll()
    replay = ViewThread(ViewServer(run_dir, live=False), "127.0.0.1:0")
    browser.get(replay.start())
    try:
        wait_for(browser, "return document.body.dataset.ready")
        t0, t1 = browser.execute_script("return [window.nacView.t0, window.nacView.t1]")
        for fraction in (0.3, 0.55, 0.8):
            offset_s = round((t1 - t0) * fraction, 1)
            scrub(browser, offset_s)
            drawn = {v["id"]: v for v in browser.execute_script(VEHICLES_JS)}
            assert set(drawn) == set(ids)
            for vid in ids:
                held = [p for p in positions(follower.records) if p["v"] == vid and p["t"] <= t0 + offset_s]
                last = max(held, key=lambda p: p["t"])
                assert (drawn[vid]["e"], drawn[vid]["n"]) == (last["e"], last["n"]), f"{vid} at +{offset_s} s"
            # the companion pack: the energy meter's last record at or before the cursor
            packs = dict(browser.execute_script("return [...document.querySelectorAll('#fleet tbody tr')].map(r => "
                                                "[r.dataset.id, r.cells[5].textContent])"))
            for vid in ids:
                metered = [f for f in follower.records if f.get("k") == "pw" and f["v"] == vid
                           and f["t"] <= t0 + offset_s]
                said = f"{max(metered, key=lambda f: f['t'])['cs']} %" if metered else "-"
                assert packs[vid] == said, f"{vid}'s companion pack at +{offset_s} s"
            assert fraction < 0.8 or all(text.endswith(" %") for text in packs.values()), packs
        assert browser.execute_script("return document.getElementById('mode').textContent") == "replay"
    finally:
        replay.stop()


def write_damaged_run(folder: Path) -> Path:
    """Two vehicles' telemetry (20 records each, 1 s apart, w1 flying east at 2 m/s), a damaged line, a half
    line at the end; no probes, no compute, no capacities."""
    from tests.unit.test_view_records import telemetry

    for vid, speed in (("master", 0.0), ("w1", 2.0)):
        (folder / vid).mkdir(parents=True)
        lines = [telemetry(1000.0 + k, speed * k, 3.0) for k in range(20)]
        lines.insert(7, "{damaged\n")
        (folder / vid / "agent.jsonl").write_text("".join(lines) + '{"t_s": 1030.0, "ki')
    return folder


def test_a_damaged_run_replays_what_is_there_and_lists_what_is_not(browser, tmp_path):
    run = write_damaged_run(tmp_path / "run")
    replay = ViewThread(ViewServer(run, live=False), "127.0.0.1:0")
    browser.get(replay.start())
    try:
        wait_for(browser, "return document.body.dataset.ready")
        scrub(browser, 10.0)
        drawn = {v["id"]: v for v in browser.execute_script(VEHICLES_JS)}
        assert drawn["w1"]["e"] == pytest.approx(20.0, abs=0.01) and drawn["master"]["e"] == pytest.approx(0.0)
        notes = browser.execute_script("return document.getElementById('notes-list').textContent")
        for expected in ("master/agent.jsonl:8: not a JSON record", "w1/agent.jsonl:22: truncated last line",
                         "missing: throughput probes", "missing: compute iterations"):
            assert expected in notes
    finally:
        replay.stop()


def test_the_job_panel_counts_per_simulated_minute_and_draws_a_cost_only_for_a_task_with_one(browser, tmp_path):
    """A 5x run's iterations, 0.3 simulated seconds apart (200 per simulated minute, 1,000 per wall minute): the
    panel says 200, as the report does; the timeline says its clock is the wall's. matmul's iterations carry no
    cost: no empty cost chart (issue 33)."""
    import json

    from tests.unit.test_view_records import telemetry

    for task, cost in (("linreg", 1.5), ("matmul", None)):
        run = tmp_path / task
        write_damaged_run(run)
        (run / "compute").mkdir()
        (run / "compute" / "compute.jsonl").write_text("".join(json.dumps(
            {"t_s": 1000.0 + 0.06 * k, "kind": "iteration", "iteration": k, "duration_s": 0.06, "cost": cost,
             "start_sim_s": 40.0 + 0.3 * k, "duration_sim_s": 0.3, "workers": {"present": [True]}}) + "\n"
            for k in range(41)))
        (run / "master" / "agent.jsonl").write_text(telemetry(1000.0, 0.0, 3.0) + telemetry(1010.0, 0.0, 3.0))
        (run / "experiment.json").write_text(json.dumps({"t_s": 999.0, "kind": "experiment", "speedup": 5.0}) + "\n")
        replay = ViewThread(ViewServer(run, live=False), "127.0.0.1:0")
        browser.get(replay.start())
        try:
            wait_for(browser, "return document.body.dataset.ready")
            scrub(browser, 5.0)
            job = browser.execute_script("return document.getElementById('job').textContent")
            assert "41 iterations, 200 per minute" in job, job
            hidden = browser.execute_script("return document.getElementById('cost-chart').hidden")
            assert hidden is (cost is None), (task, hidden)
            label = browser.execute_script("return document.getElementById('cursor-label').textContent")
            assert "wall clock (run at 5x: about 25 s simulated)" in label, label
        finally:
            replay.stop()


def test_a_reconnecting_browser_resumes_after_the_last_record_it_had(tmp_path):
    """The stream as EventSource reconnects: Last-Event-ID names the last frame held; nothing before it is
    sent again, nothing after it is skipped. The run is written in three parts, read as they come (a frame per
    vehicle and part)."""
    import json
    import urllib.request

    from tests.unit.test_view_records import telemetry

    run = tmp_path / "run"
    for vid in ("master", "w1"):
        (run / vid).mkdir(parents=True)
    viewer = ViewThread(ViewServer(run, live=True), "127.0.0.1:0")
    url = viewer.start()
    try:
        for part in range(3):
            for vid in ("master", "w1"):
                with (run / vid / "agent.jsonl").open("a") as f:
                    f.write("".join(telemetry(100.0 * part + k, float(k), 0.0) for k in range(5)))
            deadline = time.monotonic() + 10.0
            while json.loads(urllib.request.urlopen(url + "api/state", timeout=5).read())["records"] < 10 * (part + 1):
                assert time.monotonic() < deadline, f"part {part} not read"
                time.sleep(0.05)
        request = urllib.request.Request(url + "api/stream", headers={"Last-Event-ID": "3"})
        with urllib.request.urlopen(request, timeout=10) as stream:
            for raw in stream:
                if raw.startswith(b"data: ["):
                    batch = json.loads(raw[6:])
                    break
        assert [f["s"] for f in batch] == [4, 5], "frames 4 on (of 6), once each"
        assert sorted({p["t"] for p in positions(batch)}) == [200.0 + k for k in range(5)], "the third part"
    finally:
        viewer.stop()


def test_a_port_in_use_exits_1_naming_it(tmp_path):
    import socket
    import subprocess
    import sys

    run = write_damaged_run(tmp_path / "run")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run([str(Path(sys.executable).parent / "nac-ground"), "view", str(run), "--address",
                               f"127.0.0.1:{port}"], capture_output=True, text=True, timeout=30)
    assert done.returncode == 1 and f"127.0.0.1:{port}" in done.stderr and "Traceback" not in done.stderr


# ---- hostile input (issue 34): the page's numbers, ids, sizes and the Host header ---------------------------
NOTES_JS = "return document.getElementById('notes-list').textContent"
CURSOR_JS = "return [window.nacView.t0, window.nacView.t1, window.nacView.cursor, document.body.dataset.error || '']"


def load(browser, url: str) -> None:
    browser.get(url)
    wait_for(browser, "return document.body.dataset.ready || document.body.dataset.error")
    error = browser.execute_script("return document.body.dataset.error || ''")
    assert not error, f"the page stopped: {error}"


def at_values() -> list[str]:
    """`?at=` values that are not seconds inside a 19-s run: huge, infinite, not numbers, negative, text; made
    from a seeded generator besides the reported ones."""
    rng = np.random.default_rng(34)
    made = [f"{x:.6g}" for x in rng.uniform(-1e6, -0.1, 2)] + [f"1e{k}" for k in rng.integers(3, 309, 3)]
    made += ["".join(rng.choice(list("abc%<>'\"() 9e+-."), 8)) for _ in range(2)]
    return ["1e15", "Infinity", "-Infinity", "NaN", "-1", "text", "", "1e999", "0x", "end2", *made]


def test_at_values_that_are_not_seconds_inside_the_run_are_clamped_and_said(browser, tmp_path):
    run = write_damaged_run(tmp_path / "run")
    replay = ViewThread(ViewServer(run, live=False), "127.0.0.1:0")
    url = replay.start()
    try:
        for value in at_values():
            load(browser, url + "?at=" + urllib.parse.quote(value))
            t0, t1, cursor, _ = browser.execute_script(CURSOR_JS)
            assert (t0, t1) == (1000.0, 1019.0) and cursor in (t0, t1), f"?at={value!r}: cursor {cursor}"
            assert len(browser.execute_script(VEHICLES_JS)) == 2, f"?at={value!r}: vehicles drawn"
            assert f"?at={json.dumps(value[:40])}" in browser.execute_script(NOTES_JS), f"?at={value!r}: said"
            label = browser.execute_script("return document.getElementById('cursor-label').textContent")
            assert label.endswith("of 19.0 s"), label
        for value, expected in (("end", 1019.0), ("7.5", 1007.5), ("0", 1000.0), ("19", 1019.0)):
            load(browser, url + "?at=" + value)
            assert browser.execute_script(CURSOR_JS)[2] == expected
            assert "?at=" not in browser.execute_script(NOTES_JS)
    finally:
        replay.stop()


def test_records_with_wild_times_are_skipped_and_named_and_the_end_is_the_runs(browser, tmp_path):
    """Telemetry, events, probes and iterations stamped 1e15, -1e15, 1e300, a day and more from the run: skipped
    and named; `?at=end` (the screenshot's) shows the run's last positions."""
    from tests.unit.test_view_records import WILD_T_S, telemetry

    run = write_damaged_run(tmp_path / "run")
    with (run / "w1" / "agent.jsonl").open("a") as f:  # after the damaged run's half line: its own line first
        f.write("\n" + "".join(telemetry(t, 500.0, 0.0) for t in WILD_T_S))
        f.write("".join(json.dumps({"t_s": t, "kind": "mode", "value": "RTL"}) + "\n" for t in WILD_T_S))
    (run / "master" / "throughput.jsonl").write_text("".join(json.dumps(
        {"t_s": t, "kind": "throughput", "client": "master", "server": "w1"}) + "\n" for t in WILD_T_S))
    (run / "compute").mkdir()
    (run / "compute" / "compute.jsonl").write_text("".join(json.dumps(
        {"t_s": t, "kind": "iteration", "iteration": 1, "duration_s": 1.0}) + "\n" for t in WILD_T_S))
    replay = ViewThread(ViewServer(run, live=False), "127.0.0.1:0")
    try:
        load(browser, replay.start() + "?at=end")
        t0, t1, cursor, _ = browser.execute_script(CURSOR_JS)
        assert (t0, t1, cursor) == (1000.0, 1019.0, 1019.0)
        drawn = {v["id"]: v for v in browser.execute_script(VEHICLES_JS)}
        assert drawn["w1"]["e"] == pytest.approx(38.0, abs=0.01) and drawn["w1"]["t"] == 1019.0
        notes = browser.execute_script(NOTES_JS)
        assert notes.count("more than a day") == 4 * len(WILD_T_S)
        for name in ("w1/agent.jsonl", "master/throughput.jsonl", "compute/compute.jsonl"):
            assert f"{name}:1" in notes or f"{name}:2" in notes, name
        shot = tmp_path / "end.png"
        screenshot(replay.url, shot)  # what `--screenshot` and `--view` take: ?at=end
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    finally:
        replay.stop()


def test_vehicles_named_like_object_properties_draw_like_any_other(browser, tmp_path):
    """Every property name a JavaScript object has (`__proto__`, `constructor`, `toString`, ... asked of the
    browser itself), each a valid vehicle id: each drawn on the map, listed in the table with its role, its link
    and probes drawn from a master named `constructor`."""
    from tests.unit.test_view_records import telemetry

    browser.get("about:blank")
    names = browser.execute_script("return Object.getOwnPropertyNames(Object.prototype)")
    ids = sorted({*names, "__proto__", "constructor", "toString", "valueOf", "hasOwnProperty"})
    assert len(ids) >= 10
    master = "constructor"
    run = tmp_path / "run"
    for k, vid in enumerate(ids):
        (run / vid).mkdir(parents=True)
        (run / vid / "agent.jsonl").write_text("".join(telemetry(1000.0 + s, 3.0 * k, float(s)) for s in range(5)))
    (run / master / "throughput.jsonl").write_text("".join(json.dumps(
        {"t_s": 1002.0, "kind": "throughput", "client": master, "server": vid, "distance_m": 3.0,
         "end": {"sum_received": {"bits_per_second": 1e6 * (k + 1)}}}) + "\n" for k, vid in enumerate(ids)))
    (run / "experiment.json").write_text(json.dumps(
        {"t_s": 999.0, "kind": "experiment", "vehicles": [{"id": v, "role": "master" if v == master else "worker"}
                                                         for v in ids],
         "missions": {v: [] for v in ids}}) + "\n")
    replay = ViewThread(ViewServer(run, live=False), "127.0.0.1:0")
    try:
        load(browser, replay.start() + "?at=end")
        drawn = {v["id"]: v for v in browser.execute_script(VEHICLES_JS)}
        assert sorted(drawn) == ids
        assert all(drawn[vid]["e"] == pytest.approx(3.0 * k, abs=0.01) for k, vid in enumerate(ids))
        rows = browser.execute_script("return [...document.querySelectorAll('#fleet tbody tr')].map(r => "
                                      "[r.dataset.id, r.cells[1].textContent])")
        assert sorted(rows) == sorted([vid, "master" if vid == master else "worker"] for vid in ids)
        links = browser.execute_script("return [...document.querySelectorAll('#links line')].map(l => "
                                       "[l.dataset.worker, l.nextSibling.textContent])")
        assert sorted(links) == sorted([vid, f"{k + 1:.1f} Mbit/s"] for k, vid in enumerate(ids) if vid != master)
        assert browser.execute_script("return Object.getPrototypeOf({}) === Object.prototype && "
                                      "typeof ({}).toString === 'function'"), "no prototype was touched"
    finally:
        replay.stop()


def test_responses_are_bounded_pages_and_the_page_reads_them_all(browser, tmp_path, monkeypatch):
    """With the response bound made small (8 KB), /api/records answers in pages under it (X-More-Records says
    when more follow) that together are every frame once, in order; the stream's events are bounded alike; the
    page reads every page and draws the last positions."""
    from ground.view import server as server_module
    from tests.unit.test_view_records import telemetry

    monkeypatch.setattr(server_module, "MAX_RESPONSE_BYTES", 8_000)
    run = tmp_path / "run"
    for vid in ("master", "w1", "w2"):
        (run / vid).mkdir(parents=True)
    server = ViewServer(run, live=True)
    viewer = ViewThread(server, "127.0.0.1:0")
    url = viewer.start()
    try:
        for part in range(6):  # a frame per vehicle and part, each a few KB
            for k, vid in enumerate(("master", "w1", "w2")):
                with (run / vid / "agent.jsonl").open("a") as f:
                    f.write("".join(telemetry(1000.0 + part * 20 + s, 10.0 * k, float(part * 20 + s))
                                    for s in range(20)))
            deadline = time.monotonic() + 10.0
            while server.follower.record_count < 60 * (part + 1):
                assert time.monotonic() < deadline, f"part {part} not read"
                time.sleep(0.05)
        frames, after, pages = [], -1, 0
        while True:
            with urllib.request.urlopen(f"{url}api/records?after={after}", timeout=10) as answer:
                body, more = answer.read(), answer.headers["X-More-Records"]
            page = json.loads(body)
            pages += 1
            assert len(body) <= 8_000 or len(page) == 1
            frames += page
            if more != "yes":
                break
            after = page[-1]["s"]
        assert pages > 2 and [f["s"] for f in frames] == list(range(len(server.follower.records)))
        with urllib.request.urlopen(url + "api/stream?after=-1", timeout=10) as stream:
            streamed = []
            for raw in stream:
                if raw.startswith(b"data: ["):
                    assert len(raw) <= 8_000 + 10
                    streamed += json.loads(raw[6:])
                    if len(streamed) == len(frames):
                        break
        assert [f["s"] for f in streamed] == [f["s"] for f in frames]
        load(browser, url + "?at=end&snapshot=1")
        drawn = {v["id"]: v for v in browser.execute_script(VEHICLES_JS)}
        assert {vid: v["t"] for vid, v in drawn.items()} == {"master": 1119.0, "w1": 1119.0, "w2": 1119.0}
    finally:
        viewer.stop()


def vm_hwm_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1])
    raise AssertionError(f"no VmHWM for {pid}")


def view_process(run: Path, *args: str):
    import subprocess
    import sys

    proc = subprocess.Popen([str(Path(sys.executable).parent / "nac-ground"), "view", str(run), "--address",
                             "127.0.0.1:0", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert line.startswith("view: http://"), (line, proc.stderr.read() if proc.poll() is not None else "")
    return proc, line.split()[1]


def state_of(url: str) -> dict:
    return json.loads(urllib.request.urlopen(url + "api/state", timeout=10).read())


def test_a_200_mb_record_is_skipped_named_and_never_held_by_the_server(tmp_path):
    """One valid 200 MB record (a statustext), followed live and replayed: skipped and named, the records after
    it drawn, nothing of it served, and the server's peak resident memory (VmHWM) grows by less than 64 MB
    (it was 868 MB). The bound holds on any load: the line is dropped a megabyte at a time as it is read."""
    from tests.unit.test_view_records import telemetry

    run = write_damaged_run(tmp_path / "run")
    big = tmp_path / "big.jsonl"
    with big.open("w") as f:
        f.write("\n" + '{"t_s": 1025.0, "kind": "statustext", "severity": 6, "text": "')
        chunk = "x" * (1 << 20)
        for _ in range(200):
            f.write(chunk)
        f.write('"}\n' + telemetry(1026.0, 52.0, 3.0))
    size = big.stat().st_size
    proc, url = view_process(run, "--follow")
    try:
        deadline = time.monotonic() + 20.0
        while state_of(url)["records"] < 40:
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.05)
        before_kb = vm_hwm_kb(proc.pid)
        with big.open("rb") as src, (run / "w1" / "agent.jsonl").open("ab") as dst:
            shutil.copyfileobj(src, dst, 1 << 20)
        deadline = time.monotonic() + 60.0
        while (state := state_of(url))["records"] < 41:
            assert time.monotonic() < deadline and proc.poll() is None, "the record after it was not read"
            time.sleep(0.1)
        grown_kb = vm_hwm_kb(proc.pid) - before_kb
        print(f"VmHWM {before_kb} kB, grown by {grown_kb} kB")
        assert any(f"w1/agent.jsonl:23: a record of {size - 2 - len(telemetry(1026.0, 52.0, 3.0)):,} bytes" in p
                   for p in state["problems"]), state["problems"]
        body = urllib.request.urlopen(url + "api/records", timeout=10).read()
        assert len(body) < 100_000 and b"xxxxxxxx" not in body
        assert grown_kb < 64 * 1024, f"the server's peak memory grew by {grown_kb / 1024:.0f} MB"
    finally:
        proc.terminate()
        proc.wait(10)
    # Replayed: the same run read whole at start, against the run without the big line.
    (run / "w1" / "agent.jsonl").rename(tmp_path / "w1-with-big.jsonl")
    small = Path(tmp_path / "w1-with-big.jsonl").read_bytes()[:100_000].split(b"\n{\"t_s\": 1025.0")[0]
    (run / "w1" / "agent.jsonl").write_bytes(small + b"\n")
    peaks = {}
    for name in ("without", "with"):
        if name == "with":
            (run / "w1" / "agent.jsonl").unlink()
            (tmp_path / "w1-with-big.jsonl").rename(run / "w1" / "agent.jsonl")
        proc, url = view_process(run)
        try:
            state = state_of(url)
            peaks[name] = vm_hwm_kb(proc.pid)
        finally:
            proc.terminate()
            proc.wait(10)
    assert any("w1/agent.jsonl:23: a record of" in p for p in state["problems"]), state["problems"]
    print(f"replay VmHWM {peaks}")
    assert peaks["with"] - peaks["without"] < 64 * 1024, f"replay peaks {peaks}"


def raw_get(port: int, path: str, host: str | None, origin: str | None = None) -> tuple[int, str]:
    """One request with exactly the Host header given (None: none at all), as a rebinding page's would come."""
    import socket

    version = "1.1" if host is not None else "1.0"  # HTTP/1.1 without a Host: aiohttp's parser says 400 itself
    head = f"GET {path} HTTP/{version}\r\n" + (f"Host: {host}\r\n" if host is not None else "") + \
        (f"Origin: {origin}\r\n" if origin else "") + "Connection: close\r\n\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(head.encode())
        data = b""
        while chunk := sock.recv(65536):  # to the end, or a stream's headers
            data += chunk
            if path.startswith("/api/stream") and b"\r\n\r\n" in data:
                break
    status = int(data.split(b" ", 2)[1])
    return status, data.decode(errors="replace")


def spoofed_hosts(port: int) -> list[str | None]:
    rng = np.random.default_rng(3421)
    made = ["".join(rng.choice(list("abcdefghijklmnopqrstuvwxyz0123456789-"), int(n))) + ".example"
            for n in rng.integers(1, 30, 4)]
    return [None, "", "evil.example", f"evil.example:{port}", f"127.0.0.1.evil.example:{port}",
            "localhost.evil.example", f"10.0.0.1:{port}", "192.168.1.10", "[::2]", "0.0.0.0",
            "127.0.0.1@evil.example", "nac-ground.lab.evil",
            *made, *(f"{m}:{port}" for m in made)]


def test_the_view_answers_only_to_its_own_address_and_given_names(tmp_path, caplog):
    """DNS rebinding: a page of another site whose name points at this machine sends its own name as Host. On a
    loopback bind only loopback addresses and localhost are answered (every route: the page, state, records,
    the stream, static files), names given by allowed_hosts too; anything else is 421 with a sentence, a
    cross-site Origin is 403. On an every-interface bind, any address is answered and names still are not."""
    import socket

    run = write_damaged_run(tmp_path / "run")
    viewer = ViewThread(ViewServer(run, live=True, allowed_hosts=["nac-ground.lab"]), "127.0.0.1:0")
    port = int(viewer.start().rsplit(":", 1)[1].strip("/"))
    routes = ["/", "/api/state", "/api/records", "/api/stream", "/static/view.js", "/nothing"]
    try:
        for host in spoofed_hosts(port):
            for path in routes:
                status, text = raw_get(port, path, host)
                assert status == 421 and "does not answer to the host" in text, (host, path, status)
                assert "master" not in text.split("\r\n\r\n", 1)[1], "nothing of the run in the refusal"
        for host in (f"127.0.0.1:{port}", "127.0.0.1", f"localhost:{port}", "LOCALHOST", f"[::1]:{port}",
                     "127.0.0.2", "localhost.", f"nac-ground.lab:{port}", "NAC-ground.lab"):
            status, text = raw_get(port, "/api/state", host)
            assert status == 200 and '"master"' in text, (host, status, text[:200])
        assert raw_get(port, "/api/stream", f"localhost:{port}")[0] == 200
        for origin in ("http://evil.example", f"http://evil.example:{port}", "null", "http://10.0.0.1"):
            status, text = raw_get(port, "/api/state", f"127.0.0.1:{port}", origin)
            assert status == 403 and "refuses requests from pages of" in text, (origin, status)
        assert raw_get(port, "/api/state", f"127.0.0.1:{port}", f"http://localhost:{port}")[0] == 200
        with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:  # HTTP/1.1 needs a Host
            sock.sendall(b"GET /api/state HTTP/1.1\r\nConnection: close\r\n\r\n")
            assert sock.recv(100).split(b" ")[1] == b"400"
        refused = [r for r in caplog.records if r.name.startswith("ground.view")]
        assert refused and all(r.exc_info is None and "Host" in r.getMessage() for r in refused), \
            "a request aiohttp cannot parse is one line in the log, not a traceback"
    finally:
        viewer.stop()
    wildcard = ViewThread(ViewServer(run, live=False), "0.0.0.0:0")
    port = int(wildcard.start().rsplit(":", 1)[1].strip("/"))
    try:
        for host in ("10.0.0.1", f"192.168.1.10:{port}", f"127.0.0.1:{port}", "[fe80::1]", "localhost"):
            assert raw_get(port, "/api/state", host)[0] == 200, host
        for host in ("evil.example", f"evil.example:{port}", "nac-ground.lab", None):
            assert raw_get(port, "/api/state", host)[0] == 421, host
    finally:
        wildcard.stop()


def test_nac_ground_view_answers_the_names_given_with_allow_host_and_no_others(tmp_path):
    """`nac-ground view --allow-host NAME` (a real process): the name given is answered, another is 421."""
    run = write_damaged_run(tmp_path / "run")
    proc, url = view_process(run, "--allow-host", "uav-lab.local", "--allow-host", "gcs.lab")
    port = int(url.rsplit(":", 1)[1].strip("/"))
    try:
        for host in ("uav-lab.local", f"gcs.lab:{port}", f"127.0.0.1:{port}"):
            assert raw_get(port, "/api/state", host)[0] == 200, host
        for host in ("evil.example", f"uav-lab.local.evil:{port}", "lab.local"):
            assert raw_get(port, "/api/state", host)[0] == 421, host
    finally:
        proc.terminate()
        proc.communicate(timeout=20)


def test_a_real_browser_reaches_the_view_by_its_address_and_localhost(browser, tmp_path):
    run = write_damaged_run(tmp_path / "run")
    viewer = ViewThread(ViewServer(run, live=False), "127.0.0.1:0")
    url = viewer.start()
    try:
        for address in (url, url.replace("127.0.0.1", "localhost")):
            load(browser, address)
            assert len(browser.execute_script(VEHICLES_JS)) == 2, address
    finally:
        viewer.stop()


def crowded_run(folder: Path) -> Path:
    """A master at the origin and two workers near it (w1 7 m east flying north, w2 8 m east, its link where the
    master's label would go first), each probed: short links and long labels, where labels land on lines or off
    the map if anything does."""
    import json

    from tests.unit.test_view_records import telemetry

    tracks = {"master": lambda k: (0.0, 0.0), "w1": lambda k: (7.0, 0.5 * k), "w2": lambda k: (8.0, 0.8)}
    for vid, where in tracks.items():
        (folder / vid).mkdir(parents=True)
        (folder / vid / "agent.jsonl").write_text("".join(telemetry(1000.0 + k, *where(k)) for k in range(20)))
    (folder / "master" / "throughput.jsonl").write_text("".join(json.dumps(
        {"t_s": 1000.5 + k, "kind": "throughput", "client": "master", "server": w, "distance_m": 6.0,
         "end": {"sum_received": {"bits_per_second": 2.34e7}}}) + "\n" for k in range(19) for w in ("w1", "w2")))
    (folder / "experiment.json").write_text(json.dumps(
        {"t_s": 999.0, "kind": "experiment", "speedup": 1.0,
         "vehicles": [{"id": "master", "role": "master"}, {"id": "w1", "role": "worker"},
                      {"id": "w2", "role": "worker"}]}) + "\n")
    return folder


LABEL_GEOMETRY_JS = """
const map = document.getElementById('map').getBoundingClientRect();
const rect = (e) => { const r = e.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; };
const ends = (l) => { const m = l.getScreenCTM();
  return ['1', '2'].map((k) => new DOMPoint(+l.getAttribute('x' + k), +l.getAttribute('y' + k)).matrixTransform(m))
                   .map((p) => [p.x, p.y]); };
return {map: [map.left, map.top, map.right, map.bottom],
        labels: [...document.querySelectorAll('#vehicles text, #links text')].map((t) => [t.textContent, rect(t)]),
        links: [...document.querySelectorAll('#links line')].map(ends)};
"""


@pytest.mark.parametrize("size", [(1400, 860), (1024, 700), (800, 600)])
def test_labels_stay_on_the_map_and_off_the_links_at_every_page_size(browser, tmp_path, size):
    """At three page sizes, the replayed run's last moment: every vehicle and link label lies inside the map, and
    no link line passes through a label (the middle 90 % of each link, sampled every pixel, against each label's
    box shrunk by a pixel: the vehicles' own glyphs touch their labels by design). Issue 33: labels were cut at
    the map's edge and struck through by links."""
    browser.set_window_size(*size)
    replay = ViewThread(ViewServer(crowded_run(tmp_path / "run"), live=False), "127.0.0.1:0")
    browser.get(replay.start())
    try:
        wait_for(browser, "return document.body.dataset.ready")
        t0, t1 = browser.execute_script("return [window.nacView.t0, window.nacView.t1]")
        scrub(browser, t1 - t0)
        wait_for(browser, "return document.querySelectorAll('#links .link-label').length === 2")
        shown = browser.execute_script(LABEL_GEOMETRY_JS)
    finally:
        replay.stop()
    left, top, right, bottom = shown["map"]
    assert len(shown["labels"]) == 5, shown["labels"]
    for text, (x0, y0, x1, y1) in shown["labels"]:
        assert left <= x0 and x1 <= right and top <= y0 and y1 <= bottom, (size, text, shown["map"])
    for (ax, ay), (bx, by) in shown["links"]:
        steps = max(int(np.hypot(bx - ax, by - ay)), 1)
        for k in range(steps + 1):
            f = 0.05 + 0.9 * k / steps
            x, y = ax + (bx - ax) * f, ay + (by - ay) * f
            struck = [text for text, (x0, y0, x1, y1) in shown["labels"] if x0 + 1 < x < x1 - 1 and y0 + 1 < y < y1 - 1]
            assert not struck, (size, struck, (x, y))
