"""Geofence and rally points through the pure flight logic: zones from fence items, breaches by each FENCE_TYPE,
the breach action, RTL to the nearest rally point, DO_FENCE_ENABLE."""

import numpy as np
import pytest

from missions.model import Frame, MavCmd, MissionItem, MissionType
from sitl.vehicle import fence as fence_
from sitl.vehicle import guided
from sitl.vehicle.flight import CopterMode, Event, Result
from tests.unit.test_flight import HOME, run, wp
from tests.unit.test_guided import ONLY_POS, airborne, local

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced


def square(half_m: float, command=MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION) -> list[MissionItem]:
    corners = [(-half_m, -half_m), (half_m, -half_m), (half_m, half_m), (-half_m, half_m)]
    points = [wp(0, east, north) for east, north in corners]
    return [MissionItem(k, command, Frame.GLOBAL, p1=4, lat_deg=it.lat_deg, lon_deg=it.lon_deg,
                        mission_type=MissionType.FENCE) for k, it in enumerate(points)]


def test_zones_from_items_and_what_breaches_them():
    fence = fence_.fence_from_items(square(40.0) + [
        MissionItem(4, MavCmd.NAV_FENCE_CIRCLE_EXCLUSION, Frame.GLOBAL, p1=5.0, lat_deg=wp(0, 20, 20).lat_deg,
                    lon_deg=wp(0, 20, 20).lon_deg)], HOME)
    assert len(fence.inclusion_polygons) == 1 and len(fence.exclusion_circles) == 1
    every = fence_.FENCE_ALT_MAX | fence_.FENCE_CIRCLE | fence_.FENCE_POLYGON
    assert fence_.breach(fence, np.array([0.0, 0.0, 10.0]), every, 100.0, 300.0) is None
    assert "outside an inclusion" in fence_.breach(fence, np.array([0.0, 45.0, 10.0]), every, 100.0, 300.0)
    assert "exclusion" in fence_.breach(fence, np.array([21.0, 19.0, 10.0]), every, 100.0, 300.0)
    assert "FENCE_ALT_MAX" in fence_.breach(fence, np.array([0.0, 0.0, 120.0]), every, 100.0, 300.0)
    assert "FENCE_RADIUS" in fence_.breach(fence_.Fence(), np.array([0.0, 310.0, 10.0]), every, 100.0, 300.0)
    assert fence_.breach(fence, np.array([0.0, 45.0, 120.0]), 0, 100.0, 300.0) is None, "FENCE_TYPE 0: nothing"


def test_a_breach_sends_the_copter_to_the_nearest_rally_point_and_it_lands_there():
    fleet, state, params, t = airborne()
    fleet.replace_mission(0, MissionType.FENCE, square(40.0))
    rally = wp(0, 15.0, 45.0, 6.0)  # 16 m from where the breach happens, nearer than home (40 m)
    fleet.replace_mission(0, MissionType.RALLY, [MissionItem(0, MavCmd.NAV_RALLY_POINT, Frame.GLOBAL_RELATIVE_ALT,
                                                             lat_deg=rally.lat_deg, lon_deg=rally.lon_deg, alt_m=6.0,
                                                             mission_type=MissionType.RALLY)])
    fleet.enable_fence(0, 1)
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_POS, xyz=(60.0, 0.0, -10.0), state=state))  # 60 m north
    state, t = run(fleet, state, params, 200.0, t0=t, until=lambda f, s: not f.armed[0])
    texts = [str(v) for _, _, v in fleet.events]
    assert any("Fence breached: outside an inclusion zone" in x for x in texts)
    assert any("rally point" in x for x in texts) and fleet.mode[0] == CopterMode.RTL
    assert state.pos_m[0] == pytest.approx([15.0, 45.0, 0.0], abs=1.0), "landed at the rally point, not home"


def test_report_only_action_and_fence_disabled_let_the_vehicle_fly_on():
    fleet, state, params, t = airborne()
    fleet.replace_mission(0, MissionType.FENCE, square(20.0))
    params.set(0, "FENCE_ACTION", 0)
    fleet.enable_fence(0, 1)
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_POS, xyz=(40.0, 0.0, -10.0), state=state))
    state, t = run(fleet, state, params, 60.0, t0=t)
    assert fleet.mode[0] == CopterMode.GUIDED and fleet.fence_breach[0] is not None
    assert state.pos_m[0, 1] == pytest.approx(40.0, abs=0.5)
    fleet.enable_fence(0, 0)
    state, t = run(fleet, state, params, 1.0, t0=t)
    assert fleet.fence_breach[0] is None and any("breach cleared" in str(v) for _, _, v in fleet.events)
    assert fleet.enable_fence(0, 3).result != 0


def test_rtl_goes_to_the_home_set_by_do_set_home_and_arming_does_not_move_it_back():
    """DO_SET_HOME in flight ("here"), then RTL: back to that place, not to where the copter armed; relative
    altitudes count from the new home. Home set by hand survives the next arming; without it, arming moves it."""
    fleet, state, params, t = airborne()
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_POS, xyz=(20.0, 30.0, -10.0), state=state))  # 20 N, 30 E
    state, t = run(fleet, state, params, 60.0, t0=t, until=lambda f, s: np.hypot(*(s.pos_m[0, :2] - [30, 20])) < 0.2)
    assert fleet.set_home(0, None).result == Result.ACCEPTED
    assert fleet.home_m[0] == pytest.approx([30.0, 20.0, 10.0], abs=0.3)
    assert fleet.item_goal_m(0, wp(1, 0.0, 0.0, alt=5.0))[2] == pytest.approx(15.0, abs=0.3), "5 m above new home"
    fleet.setpoint(0, local(guided.LOCAL_NED, ONLY_POS, xyz=(-10.0, 0.0, -10.0), state=state))
    state, t = run(fleet, state, params, 60.0, t0=t, until=lambda f, s: s.pos_m[0, 1] < -9.8)
    fleet.set_mode(0, CopterMode.RTL)
    state, t = run(fleet, state, params, 200.0, t0=t, until=lambda f, s: not f.armed[0])
    assert state.pos_m[0, :2] == pytest.approx([30.0, 20.0], abs=1.0), "landed under the new home"
    assert any(kind is Event.HOME for _, kind, _ in fleet.events)
    fleet.set_mode(0, CopterMode.GUIDED)
    assert fleet.arm(0, True).result == Result.ACCEPTED
    assert fleet.home_m[0, :2] == pytest.approx([30.0, 20.0], abs=0.3), "a home set by hand stays"
    fleet.arm(0, False)
    assert fleet.reboot(0).result == Result.ACCEPTED
    assert fleet.arm(0, True).result == Result.ACCEPTED
    assert fleet.home_m[0] == pytest.approx(state.pos_m[0], abs=1e-6), "after a reboot, home is where it armed"
    assert fleet.set_home(0, np.array([60_000.0, 0.0, 0.0])).result == Result.FAILED, "beyond 50 km of the origin"
