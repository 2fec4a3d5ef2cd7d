"""Acceptance 1: four vehicles flown through their own missions by a pymavlink ground station."""

import threading

import numpy as np

from missions.builder import waypoint_mission
from missions.geo import lla_to_enu
from missions.model import MavCmd
from tests.integration.gcs import M

LEGS_M = [
    [(15, 10), (30, 0), (20, -15), (0, -20), (-10, 0)],
    [(-12, 12), (-25, 25), (-5, 30), (10, 20), (0, 5)],
    [(20, 20), (0, 30), (-20, 20), (-15, 0), (5, 5)],
    [(10, -10), (25, -25), (10, -35), (-10, -25), (-5, -5)],
]


def test_four_vehicles_fly_their_missions_and_report_every_item(start_sitl, gcs_for):
    sim = start_sitl(vehicles=4, speedup=40.0, spacing_m=8.0)
    trace: list[tuple[float, np.ndarray]] = []
    sim.world.step_observers.append(lambda t, s: trace.append((t, s.pos_m.copy())))
    stations, missions = [], []
    for i in range(4):
        gcs = gcs_for(sim, i)
        home = sim.homes[i]
        items = waypoint_mission(home.lat_deg, home.lon_deg, LEGS_M[i], alt_m=10.0 + 2 * i)
        assert gcs.upload(items) == M.MAV_MISSION_ACCEPTED
        assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
        assert gcs.command(MavCmd.MISSION_START, 0, 0) == M.MAV_RESULT_ACCEPTED
        stations.append(gcs)
        missions.append(items)

    reached: dict[int, list[int]] = {}

    def follow(i):
        gcs = stations[i]
        reached[i] = []
        last = len(missions[i]) - 1
        while True:
            msg = gcs.recv(["MISSION_ITEM_REACHED"], 30.0)
            if msg is None:
                return
            reached[i].append(msg.seq)
            if msg.seq == last:
                return

    threads = [threading.Thread(target=follow, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    for i in range(4):
        assert reached[i] == list(range(1, len(missions[i]))), f"vehicle {i + 1} reported {reached[i]}"

    # Landed and disarmed at the end, in the simulator's truth and in the vehicle's own heartbeat.
    for i, gcs in enumerate(stations):
        hb = gcs.recv("HEARTBEAT", 10.0, lambda m: not m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
        assert hb is not None, f"vehicle {i + 1} did not disarm after landing"
        truth = sim.truth(i)
        assert truth["on_ground"] and not truth["armed"]

    # Every waypoint was passed within its acceptance radius (WPNAV_RADIUS, 2 m).
    positions = np.stack([p for _, p in trace])  # (steps, vehicles, 3)
    for i in range(4):
        home = sim.homes[i]
        for item in missions[i][2:-1]:
            wp = lla_to_enu(item.lat_deg, item.lon_deg, home.alt_m + item.alt_m, home)
            closest = np.linalg.norm(positions[:, i, :] - wp, axis=1).min()
            assert closest <= 2.0, f"vehicle {i + 1} passed item {item.seq} at {closest:.2f} m"
    assert sim.t_s > 60  # flown in simulated time, faster than the wall clock


def test_an_ardupilot_wpl_mission_with_the_items_copters_fly_is_taken_and_flown_to_its_end(start_sitl, gcs_for):
    """The items that used to refuse the whole upload (ROI, spline, CONDITION_YAW, loiter turns, servo, delay),
    in a QGC WPL 110 file as Mission Planner writes it: accepted, flown in AUTO to the end, the turns on their
    circle."""
    from missions import loads_wpl
    from missions.geo import offset_home
    from tests.integration.gcs import take_off

    sim = start_sitl(speedup=20.0)
    gcs = gcs_for(sim)
    home = sim.homes[0]
    north, circle = offset_home(home, 0.0, 30.0), offset_home(home, 25.0, 30.0)
    rows = [
        (0, 1, 0, 16, 0, 0, 0, 0, home.lat_deg, home.lon_deg, home.alt_m),
        (1, 0, 3, 22, 0, 0, 0, 0, 0, 0, 8),
        (2, 0, 3, 201, 0, 0, 0, 0, circle.lat_deg, circle.lon_deg, 0),  # DO_SET_ROI
        (3, 0, 3, 82, 0, 0, 0, 0, north.lat_deg, north.lon_deg, 8),  # NAV_SPLINE_WAYPOINT
        (4, 0, 3, 115, 90, 30, 1, 0, 0, 0, 0),  # CONDITION_YAW
        (5, 0, 3, 183, 9, 1600, 0, 0, 0, 0, 0),  # DO_SET_SERVO
        (6, 0, 3, 18, 1, 0, 8, 0, circle.lat_deg, circle.lon_deg, 8),  # NAV_LOITER_TURNS 1 turn, 8 m
        (7, 0, 3, 93, 4, -1, -1, -1, 0, 0, 0),  # NAV_DELAY 4 s
        (8, 0, 3, 21, 0, 0, 0, 0, 0, 0, 0),
    ]
    text = "QGC WPL 110\n" + "".join("\t".join(str(v) for v in row) + "\t1\n" for row in rows)
    mission = loads_wpl(text)
    assert gcs.upload(mission.to_wire()) == M.MAV_MISSION_ACCEPTED
    take_off(gcs, 8)
    assert gcs.set_mode("AUTO") == M.MAV_RESULT_ACCEPTED
    centre = lla_to_enu(circle.lat_deg, circle.lon_deg, home.alt_m, home)
    distances = []
    while sim.truth(0)["mission_seq"] <= 6:
        position = gcs.recv("LOCAL_POSITION_NED", 20.0)
        assert position is not None and sim.t_s < 400, "the loiter turns end"
        if sim.truth(0)["mission_seq"] == 6:
            distances.append(np.hypot(position.y - centre[0], position.x - centre[1]))
    assert gcs.recv("EXTENDED_SYS_STATE", 60.0, lambda m: m.landed_state == M.MAV_LANDED_STATE_ON_GROUND)
    assert sim.truth(0)["mission_seq"] == 8 and sim.truth(0)["mission_state"] == M.MISSION_STATE_COMPLETE
    assert sim.world.fleet.servo_pwm[0] == {9: 1600}
    assert sum(abs(d - 8.0) < 1.0 for d in distances) > len(distances) / 2, "on the 8 m circle"
