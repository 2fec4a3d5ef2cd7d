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
