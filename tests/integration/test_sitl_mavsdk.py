"""Acceptance 2: MAVSDK (native binding, no server) flies a mission on the SITL as a real client."""

import threading
import time

import numpy as np
import pytest

mavsdk = pytest.importorskip("mavsdk")
from mavsdk import ComponentType, Configuration, ConnectionResult, Mavsdk, log_subscribe  # noqa: E402
from mavsdk.plugins.action import Action, ActionResult  # noqa: E402
from mavsdk.plugins.mission_raw import MissionItem, MissionRaw, MissionRawResult  # noqa: E402
from mavsdk.plugins.telemetry import LandedState, Telemetry  # noqa: E402

from missions.geo import Home, enu_to_lla, lla_to_enu  # noqa: E402


def call(start_async, timeout_s: float):
    """Run a MAVSDK *_async call and wait for its result, bounded."""
    done, box = threading.Event(), {}

    def on_result(result, _user_data):
        box["result"] = result
        done.set()

    start_async(on_result)
    assert done.wait(timeout_s), "MAVSDK call did not complete"
    return box["result"]


@pytest.fixture
def mavsdk_client():
    log_subscribe(lambda level, message, file, line: True)  # keep MAVSDK's log lines off the test output
    config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    client = Mavsdk(config)
    yield client
    client.destroy()
    config.destroy()


def wait_for_system(client, sysid: int, timeout_s: float):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for system in client.get_systems():
            if system.get_system_id() == sysid and system.has_autopilot() and system.is_connected():
                return system
        time.sleep(0.05)
    return None


def test_mavsdk_uploads_arms_flies_and_sees_the_vehicle_land(start_sitl, mavsdk_client):
    sim = start_sitl(speedup=8.0)
    port = sim.config.companion_base_port
    assert mavsdk_client.add_any_connection(f"udpin://0.0.0.0:{port}") == ConnectionResult.SUCCESS
    system = wait_for_system(mavsdk_client, 1, 10.0)
    assert system is not None, "MAVSDK did not discover the SITL vehicle"

    telemetry, mission, action = Telemetry(system), MissionRaw(system), Action(system)
    seen = {"progress": [], "landed": [], "positions": []}
    finished = threading.Event()

    def on_progress(p, _ud):
        seen["progress"].append((p.current, p.total))

    def on_landed(state, _ud):
        seen["landed"].append(state)
        airborne = LandedState.IN_AIR in seen["landed"]
        if airborne and state == LandedState.ON_GROUND:
            finished.set()

    def on_position(pos, _ud):
        seen["positions"].append((sim.t_s, pos.latitude_deg, pos.longitude_deg, pos.relative_altitude_m))

    track = []  # the truth at every simulated step: (t_s, east, north, up m about home)
    sim.world.step_observers.append(lambda t_s, state: track.append((t_s, *state.pos_m[0])))
    mission.subscribe_mission_progress(on_progress)
    telemetry.subscribe_landed_state(on_landed)
    telemetry.subscribe_position(on_position)

    home = sim.homes[0]
    waypoints = [enu_to_lla(np.array(p), home) for p in ([0, 0, 0], [15, 10, 8], [0, 20, 8], [0, 20, 0])]

    def item(seq, frame, command, lat_lon_alt):
        lat, lon, alt = lat_lon_alt
        return MissionItem(seq=seq, frame=frame, command=command, current=int(seq == 0), autocontinue=1,
                           param1=0.0, param2=0.0, param3=0.0, param4=0.0, x=int(round(float(lat) * 1e7)),
                           y=int(round(float(lon) * 1e7)), z=float(alt) - home.alt_m if frame else float(alt),
                           mission_type=0)

    items = [
        item(0, 0, 16, (home.lat_deg, home.lon_deg, home.alt_m)),  # ArduPilot's home slot
        item(1, 3, 22, (0.0, 0.0, home.alt_m + 8)),
        item(2, 3, 16, waypoints[1]),
        item(3, 3, 16, waypoints[2]),
        item(4, 3, 21, waypoints[3]),
    ]
    assert call(lambda cb: mission.upload_mission_async(items, cb), 10.0) == MissionRawResult.SUCCESS
    assert call(action.arm_async, 10.0) == ActionResult.SUCCESS
    assert call(mission.start_mission_async, 10.0) == MissionRawResult.SUCCESS

    assert finished.wait(60.0), f"vehicle did not land; landed states seen: {seen['landed'][-5:]}"
    deadline = time.monotonic() + 10
    while not mission.is_mission_finished() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert mission.is_mission_finished()  # MISSION_CURRENT.mission_state == COMPLETE
    progress = mission.mission_progress()
    assert progress.current == progress.total == 5  # MAVSDK counts the raw items, home slot included
    currents = [c for c, _ in seen["progress"]]
    assert currents == sorted(currents) and {1, 2, 3, 4} <= set(currents)
    assert LandedState.TAKING_OFF in seen["landed"] and LandedState.LANDING in seen["landed"]

    # Each position MAVSDK reported is one the vehicle truly had in the 3 simulated seconds before it arrived:
    # the telemetry's values, whatever the machine's load made of its latency.
    steps = np.array(list(track))  # one copy: the simulator goes on appending to track
    track_t, track_m = steps[:, 0], steps[:, 1:]
    errors_m = []
    for t_s, lat, lon, rel_alt_m in seen["positions"]:
        reported = lla_to_enu(lat, lon, home.alt_m + rel_alt_m, home)
        recent = track_m[(track_t <= t_s) & (track_t >= t_s - 3.0)]
        if len(recent):
            offsets = recent - reported
            nearest = np.argmin(np.linalg.norm(offsets, axis=1))
            errors_m.append((np.hypot(*offsets[nearest, :2]), abs(offsets[nearest, 2])))
    horizontal, vertical = np.array(errors_m).T
    assert len(horizontal) > 20 and horizontal.max() < 0.05 and vertical.max() < 0.05
    truth = sim.truth(0)
    final = telemetry.position()
    assert abs(final.latitude_deg - truth["lat_deg"]) < 2e-7 and abs(final.longitude_deg - truth["lon_deg"]) < 2e-7
    assert abs(final.absolute_altitude_m - truth["alt_m"]) < 0.05


def test_mavsdk_reads_integer_parameters_rtl_altitude_and_armable_health(start_sitl, mavsdk_client):
    """Parameters typed as ArduCopter stores them (MAVSDK's integer API refuses a REAL32), the RTL altitude
    MAVSDK derives from RTL_ALT, and is_armable from SYS_STATUS' PREARM_CHECK health, following the vehicle."""
    from mavsdk.plugins.param import Param

    sim = start_sitl(speedup=4.0)
    assert mavsdk_client.add_any_connection(f"udpin://0.0.0.0:{sim.config.companion_base_port}") == \
        ConnectionResult.SUCCESS
    system = wait_for_system(mavsdk_client, 1, 10.0)
    assert system is not None
    param, action, telemetry = Param(system), Action(system), Telemetry(system)
    assert param.get_param_int("RTL_ALT") == 1500 and param.get_param_int("DISARM_DELAY") == 10
    assert param.get_param_float("WPNAV_SPEED") == 500.0
    assert action.get_return_to_launch_altitude() == pytest.approx(15.0)
    param.set_param_int("RTL_ALT", 2500)
    assert sim.world.params.get(0, "RTL_ALT") == 2500 and action.get_return_to_launch_altitude() == 25.0
    param.set_param_float("WPNAV_SPEED", 3000.0)  # above the range: kept as sent, so MAVSDK's echo check passes
    assert param.get_param_float("WPNAV_SPEED") == 3000.0 and sim.world.physics.speed_xy_max_mps[0] == 20.0
    deadline = time.monotonic() + 10.0
    while not telemetry.health().is_armable and time.monotonic() < deadline:
        time.sleep(0.05)
    assert telemetry.health().is_armable, "PREARM_CHECK healthy while the checks pass"
    param.set_param_int("SIM_GPS_DISABLE", 1)
    deadline = time.monotonic() + 10.0
    while telemetry.health().is_armable and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not telemetry.health().is_armable and not sim.truth(0)["armed"]


def _until(condition, timeout_s: float, what: str) -> None:
    """Poll the simulator's truth (it has no events to await) until condition holds."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def test_mavsdk_offboard_velocity_and_position_then_a_mission_with_loiter_time(start_sitl, mavsdk_client):
    """Offboard (GUIDED on ArduPilot) velocity and position setpoints fly where they say; the Mission plugin's
    plan with loiter_time_s (which it sends as NAV_DELAY) is taken, and the copter waits there."""
    from mavsdk.plugins.mission import Mission, MissionPlan
    from mavsdk.plugins.mission import MissionItem as PlanItem
    from mavsdk.plugins.offboard import Offboard, PositionNedYaw, VelocityNedYaw

    sim = start_sitl(speedup=4.0)
    assert mavsdk_client.add_any_connection(f"udpin://0.0.0.0:{sim.config.companion_base_port}") == \
        ConnectionResult.SUCCESS
    system = wait_for_system(mavsdk_client, 1, 10.0)
    assert system is not None
    action, offboard, mission, telemetry = Action(system), Offboard(system), Mission(system), Telemetry(system)
    _until(lambda: telemetry.health().is_armable, 10.0, "armable")
    action.set_takeoff_altitude(8.0)
    action.arm()
    action.takeoff()
    _until(lambda: sim.truth(0)["rel_alt_m"] > 7.5, 30.0, "took off")
    offboard.set_velocity_ned(VelocityNedYaw(2.0, 0.0, 0.0, 0.0))
    offboard.start()
    _until(lambda: sim.truth(0)["pos_m"][1] > 6.0, 20.0, "flew north")
    truth = sim.truth(0)
    assert truth["vel_mps"][1] == pytest.approx(2.0, abs=0.2) and abs(truth["pos_m"][0]) < 0.5
    assert truth["rel_alt_m"] == pytest.approx(8.0, abs=0.5), "velocity control keeps the height"
    offboard.set_position_ned(PositionNedYaw(-10.0, 10.0, -8.0, 90.0))
    _until(lambda: np.linalg.norm(sim.truth(0)["pos_m"] - [10.0, -10.0, 8.0]) < 0.3, 40.0, "at the NED position")
    offboard.stop()

    home = sim.homes[0]
    first, second = (enu_to_lla(np.array(p), home) for p in ([0.0, 15.0, 8.0], [15.0, 15.0, 8.0]))
    plan = MissionPlan([PlanItem(float(first[0]), float(first[1]), 8.0, 5.0, False, float("nan"), float("nan"), 0, 4.0),
                        PlanItem(float(second[0]), float(second[1]), 8.0, 5.0, False, float("nan"), float("nan"), 0,
                                 float("nan"))])
    mission.upload_mission(plan)
    assert [it.command for it in sim.world.autopilots.mission(0)].count(93) == 1, "loiter_time_s arrives as NAV_DELAY"
    # every simulator step's item and position, so the delay is timed on the simulator's clock: polled from here,
    # a loaded CI run saw the delay start 0.28 s late (1.1 simulated seconds at 4x)
    steps = []
    sim.world.step_observers.append(lambda t_s, state: steps.append(
        (t_s, int(sim.world.autopilots.current_seq[0]), state.pos_m[0].copy())))
    mission.start_mission()
    # MAVSDK sends no home slot: ArduCopter takes item 0 as home and flies from item 1 (DO_CHANGE_SPEED), then the
    # NAV_DELAY of loiter_time_s where the copter is, then the second waypoint
    _until(lambda: sim.truth(0)["mission_seq"] == 3, 40.0, "the delay ended")
    delay = [(t_s, pos_m) for t_s, seq, pos_m in list(steps) if seq == 2]
    assert delay, "the copter was at the delay"
    assert delay[-1][0] - delay[0][0] == pytest.approx(4.0, abs=0.3), "waited loiter_time_s, simulated"
    assert max(np.linalg.norm(pos_m - delay[0][1]) for _, pos_m in delay) < 0.5, "where it was"
    _until(lambda: np.hypot(*(sim.truth(0)["pos_m"][:2] - [15.0, 15.0])) < 2.0, 40.0, "at the second item")
    _until(lambda: mission.is_mission_finished(), 60.0, "the mission finished")


def test_a_qgc_survey_read_by_nac_flies_its_stored_transects_in_order_and_reads_as_mavsdk_imports_it(
        start_sitl, mavsdk_client, tmp_path):
    """MAVSDK's own test plan with a survey (realworld/plan, QGC 4 format): NAC reads the survey's 12 stored items in
    its place, the items MAVSDK's import_qgroundcontrol_mission makes of the file. Uploaded by `nac-ground` (less
    PX4's SET_CAMERA_MODE, which ArduCopter refuses at upload), the copter passes every stored transect waypoint in
    order, and MAVSDK's download after the upload returns the items NAC uploaded."""
    import dataclasses

    from ground import cli
    from missions import load_mission, save_mission
    from missions.model import Frame, MavCmd, PlannedHome
    from missions.model import MissionItem as NacItem
    from tests.conftest import SHARED_DATA

    source = SHARED_DATA / "realworld" / "plan" / "mavsdk__qgroundcontrol_sample_with_survey.plan"
    if not source.exists():
        pytest.skip(f"{source} is absent (see the developers' guide)")
    ours = load_mission(source, flight=False)
    sim = start_sitl(speedup=20.0, home=Home(ours.home.lat_deg, ours.home.lon_deg, ours.home.alt_m))
    assert mavsdk_client.add_any_connection(f"udpin://0.0.0.0:{sim.config.companion_base_port}") == \
        ConnectionResult.SUCCESS
    system = wait_for_system(mavsdk_client, 1, 10.0)
    assert system is not None
    mission_raw = MissionRaw(system)
    imported = mission_raw.import_qgroundcontrol_mission(str(source)).mission_items

    def wire(deg: float) -> int:  # MISSION_ITEM_INT's 1e-7 degrees; a null (NaN) position goes as 0
        return 0 if deg != deg else round(deg * 1e7)

    assert (imported[0].x, imported[0].y) == (wire(ours.home.lat_deg), wire(ours.home.lon_deg)), "its home slot"
    assert [(i.command, i.frame, i.x, i.y) for i in imported[1:]] == \
        [(it.command, it.frame, wire(it.lat_deg), wire(it.lon_deg)) for it in ours.items], \
        "the items MAVSDK imports, in the same order"

    # ArduCopter leaves the ground in AUTO only by a NAV_TAKEOFF, which this PX4 plan leaves to PX4: one to the
    # survey's height goes first
    takeoff = NacItem(1, MavCmd.NAV_TAKEOFF, Frame.GLOBAL_RELATIVE_ALT, alt_m=ours.items[1].alt_m)
    flown = [dataclasses.replace(it, seq=k) for k, it in
             enumerate([takeoff, *(it for it in ours.items if it.command != 530)], 1)]
    plan = tmp_path / "survey.waypoints"
    home = sim.homes[0]
    save_mission(dataclasses.replace(ours, items=flown, item_info={},
                                     home=PlannedHome(home.lat_deg, home.lon_deg, home.alt_m)), plan)
    link = f"udpin:127.0.0.1:{sim.config.gcs_base_port}"
    assert cli.main(["--connect", link, "mission", "upload", str(plan)]) == 0
    done, box = threading.Event(), {}
    mission_raw.download_mission_async(lambda result, items, _ud: (box.update(result=result, items=items),
                                                                   done.set()))
    assert done.wait(20.0) and box["result"] == MissionRawResult.SUCCESS, box
    downloaded = box["items"]
    for command in (["arm"], ["mission", "start"]):
        assert cli.main(["--connect", link, *command]) == 0, command
    assert [(i.command, i.x, i.y) for i in downloaded[1:]] == \
        [(it.command, wire(it.lat_deg), wire(it.lon_deg)) for it in flown]

    transects = [it for it in flown if it.command == MavCmd.NAV_WAYPOINT]
    targets = [lla_to_enu(it.lat_deg, it.lon_deg, home.alt_m, home)[:2] for it in transects]
    passed: list[int] = []

    def watch(t_s, state):
        k = len(passed)
        if k < len(targets) and np.hypot(*(state.pos_m[0, :2] - targets[k])) < 2.0:
            passed.append(k)

    sim.world.step_observers.append(watch)
    _until(lambda: len(passed) == len(targets), 60.0, f"passed {len(passed)} of {len(targets)} waypoints")
