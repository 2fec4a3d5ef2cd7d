"""`nac-ground view --live`: vehicles watched over one MAVLink link (a telemetry radio carries them all), named
and given roles by the master agent's state feed, served as the page reads them."""

import json
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from ground.view.records import positions
from missions.geo import Home, enu_to_lla, lla_to_enu

NAC_GROUND = str(Path(sys.executable).parent / "nac-ground")


def fake_feed(answer: dict) -> tuple[socket.socket, str]:
    """A master agent's state feed (a real UDP socket answering every request with `answer`)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))

    def serve():
        try:
            while True:
                _, sender = sock.recvfrom(256)
                sock.sendto(json.dumps(answer).encode(), sender)
        except OSError:
            pass  # closed

    threading.Thread(target=serve, daemon=True).start()
    return sock, f"127.0.0.1:{sock.getsockname()[1]}"


def test_vehicles_over_one_link_are_drawn_where_the_simulator_has_them(start_sitl, tmp_path):
    sim = start_sitl(vehicles=2, speedup=5.0, port_step=0, spacing_m=12.0)
    feed_sock, feed = fake_feed({"t_s": 0, "self": {"id": "master", "role": "master", "sysid": 1},
                                 "peers": {"w1": {"id": "w1", "role": "worker", "sysid": 2, "lost": False}}})
    proc = subprocess.Popen([NAC_GROUND, "view", "--live", "--connect", f"udpin:127.0.0.1:{sim.config.gcs_base_port}",
                             "--feed", feed, "--address", "127.0.0.1:0"], stdout=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().split()[1]
        deadline = time.monotonic() + 20.0
        while True:
            state = json.loads(urllib.request.urlopen(url + "api/state", timeout=5).read())
            frames = json.loads(urllib.request.urlopen(url + "api/records", timeout=5).read())
            last = {p["v"]: p for p in positions(frames)}
            # the state was read before the records: its origin can still be unset in the round that drew both
            if (set(last) == {"master", "w1"} and state["origin"]) or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert set(last) == {"master", "w1"}, f"vehicles drawn: {sorted(last)}"
        assert state["origin"], "the map's origin: the first position heard"
        assert state["vehicles"] == {"master": {"role": "master"}, "w1": {"role": "worker"}}
        origin = Home(state["origin"]["lat_deg"], state["origin"]["lon_deg"], state["origin"]["alt_m"])
        for k, vehicle in enumerate(["master", "w1"]):
            truth = sim.truth(k)
            lat, lon, alt = enu_to_lla(truth["pos_m"], sim.homes[k])
            true_m = lla_to_enu(float(lat), float(lon), float(alt), origin)
            assert np.hypot(last[vehicle]["e"] - true_m[0], last[vehicle]["n"] - true_m[1]) < 1.0, vehicle
        assert abs(last["w1"]["e"] - last["master"]["e"] - 12.0) < 0.5, "w1's home is 12 m east"
    finally:
        proc.terminate()
        proc.wait(10)
        feed_sock.close()


def test_live_without_a_source_is_refused_with_a_sentence():
    done = subprocess.run([NAC_GROUND, "view", "--live"], capture_output=True, text=True, timeout=30)
    assert done.returncode == 2 and "--connect URI or a --feed" in done.stderr
    done = subprocess.run([NAC_GROUND, "view"], capture_output=True, text=True, timeout=30)
    assert done.returncode == 2 and "give a RUN_DIR" in done.stderr


def test_a_live_screenshot_ends_with_the_vehicles_drawn_or_says_nothing_was_heard(start_sitl, tmp_path):
    """`view --live --screenshot` once served for ever; it now listens until a vehicle is drawn (10 s at most)."""
    from ground.view.serve import chromium
    from tests.conftest import free_port

    if not chromium():
        pytest.skip("no Chromium (.ci/run installs it)")
    sim = start_sitl(vehicles=1, speedup=5.0)
    links = ((f"udpin:127.0.0.1:{sim.config.gcs_base_port}", True), (f"udpin:127.0.0.1:{free_port()}", False))
    for uri, heard in links:
        shot = tmp_path / f"live-{heard}.png"
        done = subprocess.run([NAC_GROUND, "view", "--live", "--connect", uri, "--address", "127.0.0.1:0",
                               "--screenshot", str(shot)], capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, done.stderr
        assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"view: {shot}" in done.stdout
        assert ("nothing heard on" in done.stdout) is not heard, done.stdout
