"""Build missions from local offsets in metres: the example and scenario generators, tests and benchmarks.

Positions are east/north metres from a home on the tangent plane (missions.geo), rounded to 1e-8 degree (about a
millimetre) so the files written from them read well.
"""

from __future__ import annotations

import math

from missions.geo import offset_home
from missions.model import Frame, MavCmd, Mission, MissionItem, PlannedHome


def offset(origin: PlannedHome, east_m: float, north_m: float) -> PlannedHome:
    """A point east_m/north_m from origin, at origin's altitude."""
    point = offset_home(origin, east_m, north_m)
    return PlannedHome(round(point.lat_deg, 8), round(point.lon_deg, 8), origin.alt_m)


class Builder:
    """Items numbered 1..n in the order added; NaN yaw means 'keep heading', as QGC writes it."""

    def __init__(self, home: PlannedHome):
        self.home, self.items = home, []

    def _add(self, command: int, frame: int, *params: float, at: PlannedHome | None = None, alt_m: float = 0.0):
        lat, lon = (at.lat_deg, at.lon_deg) if at else (0.0, 0.0)
        p = [float(x) for x in (*params, 0.0, 0.0, 0.0, 0.0)[:4]]
        self.items.append(MissionItem(len(self.items) + 1, command, frame, *p, lat_deg=lat, lon_deg=lon, alt_m=alt_m))

    def takeoff(self, alt_m: float) -> Builder:
        self._add(MavCmd.NAV_TAKEOFF, Frame.GLOBAL_RELATIVE_ALT, 0, 0, 0, math.nan, at=self.home, alt_m=alt_m)
        return self

    def speed(self, ground_speed_mps: float) -> Builder:
        self._add(MavCmd.DO_CHANGE_SPEED, Frame.MISSION, 1, ground_speed_mps, -1, 0)  # type 1 = ground speed
        return self

    def waypoint(self, east_m: float, north_m: float, alt_m: float) -> Builder:
        self._add(MavCmd.NAV_WAYPOINT, Frame.GLOBAL_RELATIVE_ALT, 0, 0, 0, math.nan,
                  at=offset(self.home, east_m, north_m), alt_m=alt_m)
        return self

    def hold(self, east_m: float, north_m: float, alt_m: float, seconds: float) -> Builder:
        self._add(MavCmd.NAV_LOITER_TIME, Frame.GLOBAL_RELATIVE_ALT, seconds, 0, 0, 0,
                  at=offset(self.home, east_m, north_m), alt_m=alt_m)
        return self

    def land(self, east_m: float, north_m: float) -> Builder:
        self._add(MavCmd.NAV_LAND, Frame.GLOBAL_RELATIVE_ALT, 0, 0, 0, math.nan,
                  at=offset(self.home, east_m, north_m), alt_m=0.0)
        return self

    def mission(self) -> Mission:
        return Mission(home=self.home, items=self.items)


def waypoint_mission(home_lat: float, home_lon: float, offsets_m: list[tuple[float, float]], alt_m: float = 10.0,
                     land: bool = True) -> list[MissionItem]:
    """The items a ground station uploads: home slot (item 0, as ArduPilot numbers them), takeoff, one waypoint per
    (east, north) offset from home in metres, then land."""
    home = PlannedHome(home_lat, home_lon, 0.0)
    items = [MissionItem(0, MavCmd.NAV_WAYPOINT, Frame.GLOBAL, lat_deg=home_lat, lon_deg=home_lon),
             MissionItem(1, MavCmd.NAV_TAKEOFF, Frame.GLOBAL_RELATIVE_ALT_INT, alt_m=alt_m)]
    for east, north in offsets_m:
        wp = offset_home(home, east, north)
        items.append(MissionItem(len(items), MavCmd.NAV_WAYPOINT, Frame.GLOBAL_RELATIVE_ALT_INT,
                                 lat_deg=wp.lat_deg, lon_deg=wp.lon_deg, alt_m=alt_m))
    if land:
        items.append(MissionItem(len(items), MavCmd.NAV_LAND, Frame.GLOBAL_RELATIVE_ALT_INT))
    return items
