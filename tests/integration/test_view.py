"""The web view in a real browser: Debian's headless Chromium driven through chromedriver by selenium. The live
page of a short SITL experiment against the simulator's truth, then the finished run replayed and scrubbed."""

import shutil
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from ground.view.records import RunFollower, positions
from ground.view.serve import CHROMIUM_FLAGS, ViewThread, chromium
from ground.view.server import ViewServer
from missions import save_mission
from missions.geo import Home, enu_to_lla, lla_to_enu
from sitl.experiment.runner import Experiment, Outcome, save_screenshot
from sitl.experiment.scenario import load_scenario
from sitl.scenarios.generate import at, hover, route
from tests.conftest import allocate_base_port
from tests.integration.test_experiment import write_scenario

CHROMEDRIVER = shutil.which("chromedriver")
pytestmark = pytest.mark.skipif(not (chromium() and CHROMEDRIVER),
                                reason="Chromium and chromedriver are not installed (.ci/run installs them)")
VEHICLES_JS = """return [...document.querySelectorAll('#vehicles .vehicle')].map(g => ({
    id: g.dataset.id, e: +g.dataset.e, n: +g.dataset.n, t: +g.dataset.t, tb: +g.dataset.tb}));"""


@pytest.fixture
def browser(tmp_path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium()
    for flag in [*CHROMIUM_FLAGS, "--window-size=1400,860", f"--user-data-dir={tmp_path / 'profile'}"]:
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    driver.set_page_load_timeout(30)
    yield driver
    driver.quit()


def wait_for(browser, script: str, timeout_s: float = 20.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = browser.execute_script(script)
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"the page never answered {script!r} within {timeout_s} s")


def out_and_back_scenario(folder: Path) -> Path:
    """write_scenario's fleet, but w1 flies 120 m out (the channel's median range is 47 m) and back at 12 m/s."""
    path = write_scenario(folder, duration_s=45.0)
    save_mission(route(at(5, 0), 5.0, [(120.0, 0.0), (5.0, 0.0)], speed_mps=12.0), folder / "w1.plan")
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
    assert iterations[-1] > iterations[len(iterations) // 4] > 0, "the iteration counter advanced"
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
            browser.execute_script("const s = document.getElementById('cursor'); s.value = arguments[0];"
                                   "s.dispatchEvent(new Event('input'));", offset_s)
            drawn = {v["id"]: v for v in browser.execute_script(VEHICLES_JS)}
            assert set(drawn) == set(ids)
            for vid in ids:
                held = [p for p in positions(follower.records) if p["v"] == vid and p["t"] <= t0 + offset_s]
                last = max(held, key=lambda p: p["t"])
                assert (drawn[vid]["e"], drawn[vid]["n"]) == (last["e"], last["n"]), f"{vid} at +{offset_s} s"
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
        browser.execute_script("const s = document.getElementById('cursor'); s.value = 10;"
                               "s.dispatchEvent(new Event('input'));")
        drawn = {v["id"]: v for v in browser.execute_script(VEHICLES_JS)}
        assert drawn["w1"]["e"] == pytest.approx(20.0, abs=0.01) and drawn["master"]["e"] == pytest.approx(0.0)
        notes = browser.execute_script("return document.getElementById('notes-list').textContent")
        for expected in ("master/agent.jsonl:8: not a JSON record", "w1/agent.jsonl:22: truncated last line",
                         "missing: throughput probes", "missing: compute iterations"):
            assert expected in notes
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
