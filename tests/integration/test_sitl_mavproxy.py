"""MAVProxy (its core, installed without its GUI dependencies) drives the SITL as a user at its prompt would:
parameters over the parameter protocol once MAVFTP is refused at once, GUIDED velocity and position commands,
an ArduPilot WPL mission loaded and flown in AUTO with pause and resume. Each checks the simulator's truth."""

import queue
import re
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from missions.geo import offset_home

MAVPROXY = shutil.which("mavproxy.py") or str(Path(__file__).resolve().parents[2] / ".venv" / "bin" / "mavproxy.py")
pytestmark = pytest.mark.skipif(not Path(MAVPROXY).exists(), reason="MAVProxy is not installed (make test installs it)")


class MavProxy:
    """MAVProxy at its prompt: commands in on stdin, every output line collected for expect()."""

    def __init__(self, port: int, state_dir: Path):
        self.proc = subprocess.Popen([MAVPROXY, f"--master=udpin:127.0.0.1:{port}", f"--state-basedir={state_dir}"],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, cwd=state_dir)
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line.rstrip())

    def send(self, command: str) -> None:
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def expect(self, pattern: str, timeout_s: float = 15.0) -> re.Match:
        """The first output line from now on that matches, or fail naming what was seen."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                break
            self.seen.append(line)
            match = re.search(pattern, line)
            if match:
                return match
        raise AssertionError(f"MAVProxy never printed /{pattern}/ within {timeout_s} s; last lines: {self.seen[-15:]}")

    def close(self) -> None:
        self.proc.kill()  # MAVProxy's module threads ignore SIGTERM
        self.proc.wait(10)


@pytest.fixture
def mavproxy(tmp_path):
    started: list[MavProxy] = []

    def start(sim) -> MavProxy:
        proxy = MavProxy(sim.config.gcs_base_port, tmp_path)
        started.append(proxy)
        proxy.expect(r"online system 1")
        return proxy

    yield start
    for proxy in started:
        proxy.close()


def until(condition, timeout_s: float, what: str) -> None:
    """Poll the simulator's truth (it has no events to await) until condition holds."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def wpl(rows) -> str:
    """A QGC WPL 110 file, as Mission Planner and MAVProxy write them."""
    return "QGC WPL 110\n" + "".join("\t".join(str(v) for v in r) + "\t1\n" for r in rows)


def load_mission(proxy: MavProxy, sim, path: Path, rows) -> None:
    """`wp load` of the rows as a WPL file, until the whole mission is on the vehicle."""
    path.write_text(wpl(rows))
    proxy.send(f"wp load {path}")
    proxy.expect(r"Sent all \d+ waypoints|Loaded \d+ waypoints", 15.0)
    until(lambda: len(sim.world.autopilots.mission(0)) == len(rows), 10.0, "the mission is on the vehicle")


def take_off(proxy: MavProxy, alt_m: float) -> None:
    proxy.send("mode guided")
    proxy.expect(r"DO_SET_MODE: ACCEPTED")
    proxy.send("arm throttle")
    proxy.expect(r"COMPONENT_ARM_DISARM: ACCEPTED")
    proxy.send(f"takeoff {alt_m:g}")
    proxy.expect(r"Takeoff complete", 30.0)


def test_parameters_fetch_without_an_ftp_wait_and_an_integer_parameter_is_set(start_sitl, mavproxy):
    sim = start_sitl(speedup=4.0)
    proxy = mavproxy(sim)
    proxy.expect(r"Received \d+ parameters", 10.0)
    assert not any("FTP: request timed out" in line for line in proxy.seen), "MAVFTP answered at once"
    proxy.send("param set DISARM_DELAY 5")
    until(lambda: sim.world.params.get(0, "DISARM_DELAY") == 5, 10.0, "the vehicle took the value")
    for _ in range(20):  # MAVProxy's own copy follows the vehicle's echo a moment later
        proxy.send("param show DISARM_DELAY")
        if float(proxy.expect(r"DISARM_DELAY\s+(\S+)").group(1)) == 5:
            break
    else:
        raise AssertionError("MAVProxy never showed DISARM_DELAY 5")
    proxy.send("param show FENCE_ENABLE")
    proxy.expect(r"FENCE_ENABLE\s+0")
    assert not any("fence breach" in line.lower() for line in proxy.seen)


def test_guided_velocity_and_position_commands_move_the_vehicle(start_sitl, mavproxy):
    """MAVProxy's `velocity` and `position` are BODY_NED setpoints: forward means where the nose points."""
    sim = start_sitl(speedup=10.0)
    proxy = mavproxy(sim)
    take_off(proxy, 10)
    proxy.send("setyaw 90 0 0")  # CONDITION_YAW: face east
    until(lambda: abs(np.degrees(sim.world.state.yaw_rad[0]) - 90) < 1.0, 15.0, "turned east")
    proxy.send("velocity 2 0 0")
    until(lambda: sim.truth(0)["pos_m"][0] > 3.0, 15.0, "flew forward, that is east")
    truth = sim.truth(0)
    assert abs(truth["pos_m"][1]) < 0.5 and abs(truth["pos_m"][2] - 10.0) < 0.5, "not north, not down"
    proxy.expect(r"no velocity setpoint for 3 s, stopping", 15.0)
    until(lambda: np.hypot(*sim.truth(0)["vel_mps"][:2]) < 0.1, 15.0, "stopped after 3 s")
    start = sim.truth(0)["pos_m"]
    proxy.send("position 0 5 -2")  # 5 m to the right of an east-facing copter (south), 2 m up
    until(lambda: np.linalg.norm(sim.truth(0)["pos_m"] - (start + [0.0, -5.0, 2.0])) < 0.3, 30.0,
          "went to the body-frame offset")


def test_a_wpl_mission_flies_in_auto_and_pauses_and_resumes(start_sitl, mavproxy, tmp_path):
    sim = start_sitl(speedup=10.0)
    proxy = mavproxy(sim)
    home = sim.homes[0]
    far = offset_home(home, 0.0, 60.0)
    rows = [(0, 1, 0, 16, 0, 0, 0, 0, home.lat_deg, home.lon_deg, home.alt_m),
            (1, 0, 3, 22, 0, 0, 0, 0, 0, 0, 10),
            (2, 0, 3, 16, 0, 0, 0, 0, far.lat_deg, far.lon_deg, 10),
            (3, 0, 3, 20, 0, 0, 0, 0, 0, 0, 0)]
    load_mission(proxy, sim, tmp_path / "out-and-back.waypoints", rows)
    take_off(proxy, 10)
    proxy.send("mode auto")
    until(lambda: sim.truth(0)["pos_m"][1] > 15.0, 30.0, "flying the mission")
    proxy.send("pause")
    until(lambda: sim.truth(0)["mission_state"] == 4 and np.hypot(*sim.truth(0)["vel_mps"][:2]) < 0.05, 30.0,
          "paused and holding")
    held = sim.truth(0)["pos_m"][1]
    assert held < 55.0
    proxy.send("resume")
    until(lambda: sim.truth(0)["pos_m"][1] > 58.0, 60.0, "went on to the far waypoint")
    until(lambda: not sim.truth(0)["armed"], 120.0, "returned, landed and disarmed")
    assert np.hypot(*sim.truth(0)["pos_m"][:2]) < 1.0


def test_a_fence_breach_sends_the_copter_to_the_rally_point(start_sitl, mavproxy, tmp_path):
    """Fence and rally loaded by MAVProxy from WPL files, FENCE_ENABLE set at its prompt: flying out of the
    inclusion square, the copter says so, switches to RTL and lands at the rally point, nearer than home."""
    sim = start_sitl(speedup=10.0)
    proxy = mavproxy(sim)
    home = sim.homes[0]
    corners = [offset_home(home, e, n) for e, n in ((-40, -40), (40, -40), (40, 40), (-40, 40))]
    fence_file, rally_file = tmp_path / "fence.txt", tmp_path / "rally.txt"
    fence_file.write_text(wpl([(k, 0, 0, 5001, 4, 0, 0, 0, c.lat_deg, c.lon_deg, 0) for k, c in enumerate(corners)]))
    rally = offset_home(home, 15.0, 45.0)
    rally_file.write_text(wpl([(0, 0, 3, 5100, 0, 0, 0, 0, rally.lat_deg, rally.lon_deg, 8)]))
    proxy.send(f"fence load {fence_file}")
    until(lambda: len(sim.world.autopilots.mission(0, 1)) == 4, 15.0, "the fence is on the vehicle")
    proxy.send(f"rally load {rally_file}")
    until(lambda: len(sim.world.autopilots.mission(0, 2)) == 1, 15.0, "the rally point is on the vehicle")
    proxy.expect(r"Received \d+ parameters", 15.0)
    proxy.send("param set FENCE_ENABLE 1")
    until(lambda: sim.world.params.get(0, "FENCE_ENABLE") == 1, 10.0, "fence enabled")
    take_off(proxy, 10)
    proxy.send("position 60 0 0")  # 60 m forward (north)
    proxy.expect(r"Fence breached: outside an inclusion zone", 60.0)
    proxy.expect(r"RTL>|Mode RTL", 15.0)
    until(lambda: not sim.truth(0)["armed"], 120.0, "landed and disarmed")
    assert np.hypot(*(sim.truth(0)["pos_m"][:2] - [15.0, 45.0])) < 1.5, "at the rally point, not home"


def test_a_wpl_mission_with_roi_spline_yaw_servo_turns_and_delay_flies_in_auto_to_its_end(start_sitl, mavproxy,
                                                                                          tmp_path):
    """The items that used to refuse the whole upload, loaded by `wp load` from a QGC WPL 110 file: the nose on
    the region of interest along the spline, CONDITION_YAW's heading, the servo, one turn on the 8 m circle, the
    4 s delay, then RTL; every item reached, in the vehicle's truth."""
    sim = start_sitl(speedup=10.0)
    proxy = mavproxy(sim)
    home = sim.homes[0]
    north, circle = offset_home(home, 0.0, 30.0), offset_home(home, 25.0, 30.0)
    rows = [(0, 1, 0, 16, 0, 0, 0, 0, home.lat_deg, home.lon_deg, home.alt_m),
            (1, 0, 3, 22, 0, 0, 0, 0, 0, 0, 8),
            (2, 0, 3, 201, 0, 0, 0, 0, circle.lat_deg, circle.lon_deg, 0),  # DO_SET_ROI
            (3, 0, 3, 82, 0, 0, 0, 0, north.lat_deg, north.lon_deg, 8),  # NAV_SPLINE_WAYPOINT
            (4, 0, 3, 115, 90, 30, 1, 0, 0, 0, 0),  # CONDITION_YAW to 90 degrees at 30 deg/s, clockwise
            (5, 0, 3, 183, 9, 1600, 0, 0, 0, 0, 0),  # DO_SET_SERVO 9 to 1600 us
            (6, 0, 3, 18, 1, 0, 8, 0, circle.lat_deg, circle.lon_deg, 8),  # NAV_LOITER_TURNS: 1 turn, 8 m
            (7, 0, 3, 93, 4, -1, -1, -1, 0, 0, 0),  # NAV_DELAY 4 s
            (8, 0, 3, 20, 0, 0, 0, 0, 0, 0, 0)]  # NAV_RETURN_TO_LAUNCH
    load_mission(proxy, sim, tmp_path / "items.waypoints", rows)
    take_off(proxy, 8)
    # The truth at every simulated step, recorded by the simulator itself: sampling it from here would see a
    # loaded machine's gaps (at 10x, 0.1 s of wall time is a second of flight).
    steps = []  # (t_s, item, east/north m, compass heading deg)
    sim.world.step_observers.append(lambda t_s, state: steps.append(
        (t_s, int(sim.world.autopilots.current_seq[0]), state.pos_m[0, :2].copy(), np.degrees(state.yaw_rad[0]))))
    proxy.send("mode auto")
    until(lambda: not sim.truth(0)["armed"] or sim.t_s > 400, 120.0, "the mission ends")
    assert not sim.truth(0)["armed"], f"the mission ends; stuck at item {sim.truth(0)['mission_seq']}"
    centre = np.array([25.0, 30.0])
    off_roi_deg, circle_m, delay_t_s, seqs = [], [], [], set()
    for t_s, seq, pos, yaw_deg in list(steps):  # a copy: the simulator goes on appending
        seqs.add(seq)
        if seq == 3 and np.hypot(*(centre - pos)) > 5.0:
            bearing_deg = np.degrees(np.arctan2(*(centre - pos)))
            off_roi_deg.append(abs((yaw_deg - bearing_deg + 180.0) % 360.0 - 180.0))
        if seq == 6:
            circle_m.append(np.hypot(*(pos - centre)))
        if seq == 7:
            delay_t_s.append(t_s)
    assert {3, 6, 7, 8} <= seqs and sim.truth(0)["mission_state"] == 5, "every item, mission complete"
    assert np.median(off_roi_deg) < 5.0, "the nose on the region of interest along the spline"
    assert sum(abs(d - 8.0) < 1.0 for d in circle_m) > len(circle_m) / 2, "the turn on the 8 m circle"
    assert 3.8 <= delay_t_s[-1] - delay_t_s[0] <= 4.2, "NAV_DELAY held for its 4 s"
    assert sim.world.autopilots.servo_pwm[0] == {9: 1600}
    assert np.hypot(*sim.truth(0)["pos_m"][:2]) < 1.0, "RTL landed at home"


def test_mode_circle_goes_round_circle_radius_ahead_at_circle_rate(start_sitl, mavproxy):
    """ArduCopter's CIRCLE from MAVProxy: the centre CIRCLE_RADIUS ahead of the nose, the vehicle on the circle at
    CIRCLE_RATE (issue 33: it was "unsupported mode"). Judged on the simulator's own steps over a whole turn."""
    sim = start_sitl(speedup=10.0)
    proxy = mavproxy(sim)
    proxy.expect(r"Received \d+ parameters", 10.0)
    proxy.send("param set CIRCLE_RADIUS 2000")
    until(lambda: sim.world.params.get(0, "CIRCLE_RADIUS") == 2000, 10.0, "the vehicle took the radius")
    take_off(proxy, 10)
    start, yaw = sim.truth(0)["pos_m"].copy(), float(sim.world.state.yaw_rad[0])
    steps = []  # (t_s, east/north m)
    sim.world.step_observers.append(lambda t_s, state: steps.append((t_s, state.pos_m[0, :2].copy())))
    proxy.send("mode circle")
    until(lambda: sim.truth(0)["mode"] == "CIRCLE", 10.0, "in CIRCLE")
    t0 = sim.t_s
    until(lambda: sim.t_s > t0 + 5.0 + 360 / 20, 60.0, "a whole turn at 20 deg/s after settling")
    centre = start[:2] + 20.0 * np.array([np.sin(yaw), np.cos(yaw)])
    on_circle = [np.hypot(*(p - centre)) for t, p in list(steps) if t > t0 + 5.0]
    assert len(on_circle) > 100 and all(19.0 <= r <= 21.0 for r in on_circle), \
        f"radius {min(on_circle):.2f}-{max(on_circle):.2f} m about the centre 20 m ahead"
    turning = [(t, p) for t, p in list(steps) if t > t0 + 5.0]
    bearings = np.unwrap([np.arctan2(*(p - centre)) for _, p in turning])
    rate_dps = np.degrees(bearings[-1] - bearings[0]) / (turning[-1][0] - turning[0][0])
    # as ArduCopter's circle controller: CIRCLE_RATE, capped so that the speed stays within WPNAV_SPEED
    expected_dps = min(20.0, np.degrees(sim.world.params.get(0, "WPNAV_SPEED") / 100.0 / 20.0))
    assert rate_dps == pytest.approx(expected_dps, rel=0.05), f"{rate_dps:.1f} deg/s clockwise"
    proxy.send("mode acro")
    proxy.expect(r"ACRO not in this SITL")
    assert sim.truth(0)["mode"] == "CIRCLE", "a mode it does not fly is refused, the vehicle goes on"


def test_mode_smart_rtl_flies_the_way_back_it_came_and_lands_where_it_armed(start_sitl, mavproxy):
    """MAVProxy flies the copter 30 m north, then 30 m east (GUIDED); SMART_RTL returns by the corner, not
    straight home as RTL would, and lands and disarms where it armed (issue 33: it was "unsupported mode")."""
    sim = start_sitl(speedup=10.0)
    proxy = mavproxy(sim)
    home = sim.homes[0]
    take_off(proxy, 10)
    for east, north in ((0.0, 30.0), (30.0, 30.0)):
        there = offset_home(home, east, north)
        proxy.send(f"guided {there.lat_deg:.7f} {there.lon_deg:.7f} 10")
        until(lambda e=east, n=north: np.hypot(*(sim.truth(0)["pos_m"][:2] - [e, n])) < 1.0, 60.0,
              f"at {east:g} m east, {north:g} m north")
    steps = []
    sim.world.step_observers.append(lambda t_s, state: steps.append(state.pos_m[0].copy()))
    proxy.send("mode smart_rtl")
    until(lambda: not sim.truth(0)["armed"], 120.0, "landed and disarmed")
    way_back = np.array(steps)
    corner_m = np.min(np.hypot(way_back[:, 0] - 0.0, way_back[:, 1] - 30.0))
    assert corner_m < 3.0, f"came back by the corner: {corner_m:.1f} m from it at best"
    assert np.hypot(*sim.truth(0)["pos_m"][:2]) < 2.0 and sim.truth(0)["on_ground"], "landed where it armed"
    assert sim.truth(0)["mode"] == "SMART_RTL"
