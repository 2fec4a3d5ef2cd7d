"""Geofence and rally points as ArduCopter uses them (pure): the fence items and parameters make a fence, a
position breaches it or not, and RTL goes to the nearest rally point (or home).

FENCE_TYPE is a bitmask: 1 the altitude ceiling FENCE_ALT_MAX, 2 the circle of FENCE_RADIUS about home, 4 the
uploaded polygons and circles (inside every inclusion zone, outside every exclusion zone). Positions are ENU
metres about the vehicle's home.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from missions.geo import Home, lla_to_enu
from missions.model import MavCmd, MissionItem

FENCE_ALT_MAX, FENCE_CIRCLE, FENCE_POLYGON = 1, 2, 4


@dataclass
class Fence:
    inclusion_polygons: list[np.ndarray] = field(default_factory=list)  # each (k, 2) east, north
    exclusion_polygons: list[np.ndarray] = field(default_factory=list)
    inclusion_circles: list[tuple[np.ndarray, float]] = field(default_factory=list)  # (centre, radius_m)
    exclusion_circles: list[tuple[np.ndarray, float]] = field(default_factory=list)

    @property
    def has_zones(self) -> bool:
        return bool(self.inclusion_polygons or self.exclusion_polygons or self.inclusion_circles
                    or self.exclusion_circles)


def _en(item: MissionItem, home: Home) -> np.ndarray:
    return lla_to_enu(item.lat_deg, item.lon_deg, home.alt_m, home)[:2]


def fence_from_items(items: list[MissionItem], home: Home) -> Fence:
    """The zones of an uploaded fence list: polygon vertices come in runs of param1 vertices each."""
    fence = Fence()
    k = 0
    while k < len(items):
        item = items[k]
        if item.command in (MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION, MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION):
            count = max(int(item.p1), 1)
            run = [it for it in items[k:k + count] if it.command == item.command]
            polygon = np.array([_en(it, home) for it in run])
            if len(polygon) >= 3:
                inclusion = item.command == MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION
                (fence.inclusion_polygons if inclusion else fence.exclusion_polygons).append(polygon)
            k += len(run)
            continue
        if item.command == MavCmd.NAV_FENCE_CIRCLE_INCLUSION:
            fence.inclusion_circles.append((_en(item, home), float(item.p1)))
        elif item.command == MavCmd.NAV_FENCE_CIRCLE_EXCLUSION:
            fence.exclusion_circles.append((_en(item, home), float(item.p1)))
        k += 1
    return fence


def inside_polygon(point: np.ndarray, polygon: np.ndarray) -> bool:
    """Even-odd rule: a ray east from the point crosses the boundary an odd number of times."""
    x, y = point
    inside = False
    for (x1, y1), (x2, y2) in zip(polygon, np.roll(polygon, -1, axis=0), strict=True):
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def breach(fence: Fence, pos_m: np.ndarray, kinds: int, alt_max_m: float, radius_m: float) -> str | None:
    """Why the position is outside the fence (said as ArduCopter's message would), or None."""
    en = pos_m[:2]
    if kinds & FENCE_ALT_MAX and pos_m[2] > alt_max_m:
        return f"altitude {pos_m[2]:.0f} m above FENCE_ALT_MAX {alt_max_m:g} m"
    if kinds & FENCE_CIRCLE and float(np.hypot(*en)) > radius_m:
        return f"{float(np.hypot(*en)):.0f} m from home, beyond FENCE_RADIUS {radius_m:g} m"
    if kinds & FENCE_POLYGON:
        if any(not inside_polygon(en, poly) for poly in fence.inclusion_polygons) or any(
                float(np.hypot(*(en - c))) > r for c, r in fence.inclusion_circles):
            return "outside an inclusion zone"
        if any(inside_polygon(en, poly) for poly in fence.exclusion_polygons) or any(
                float(np.hypot(*(en - c))) < r for c, r in fence.exclusion_circles):
            return "inside an exclusion zone"
    return None


def rally_target(rally: list[MissionItem], origin: Home, home_m: np.ndarray, here_m: np.ndarray,
                 include_home: bool, limit_km: float) -> np.ndarray | None:
    """Where RTL goes (east, north, up about the origin): the nearest rally point (its altitude above home), or
    home when it is nearer and RALLY_INCL_HOME allows it, or when every rally point is beyond RALLY_LIMIT_KM (0:
    no limit); None for home."""
    best, best_m = None, float(np.hypot(*(here_m[:2] - home_m[:2]))) if include_home else float("inf")
    for item in rally:
        point = np.append(_en(item, origin), item.alt_m + home_m[2])
        distance_m = float(np.hypot(*(point[:2] - here_m[:2])))
        if limit_km > 0 and distance_m > limit_km * 1000.0:
            continue
        if distance_m < best_m:
            best, best_m = point, distance_m
    return best
