"""The one geodesy: WGS-84 latitude/longitude/altitude <-> ECEF <-> local ENU metres about a home (pure, numpy).

Used by the SITL (vehicle positions), the companion (distances between vehicles), the log analysis (tracks in
local metres) and the mission builders; the file formats in this package stay stdlib-only and do not import it.

East/north are the exact tangent-plane coordinates at home (through ECEF); up is the altitude difference, so a
vehicle holding 10 m "up" reports 10 m above home anywhere in the flying area instead of rising with the earth's
curvature (about 2 m at 5 km). Within 5 km of home a round trip is exact to the millimetre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


@dataclass(frozen=True)
class Home:
    lat_deg: float
    lon_deg: float
    alt_m: float  # AMSL (treated as ellipsoidal height; the difference does not matter locally)


def lla_to_ecef(lat_deg, lon_deg, alt_m):
    lat = np.radians(lat_deg)
    lon = np.radians(lon_deg)
    sin_lat = np.sin(lat)
    n_m = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    x = (n_m + alt_m) * np.cos(lat) * np.cos(lon)
    y = (n_m + alt_m) * np.cos(lat) * np.sin(lon)
    z = (n_m * (1.0 - WGS84_E2) + alt_m) * sin_lat
    return np.stack([x, y, z], axis=-1)


def ecef_m(lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
    """lla_to_ecef for one point in plain floats: the agent asks it per datagram, where numpy's overhead shows."""
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n_m = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
    return ((n_m + alt_m) * math.cos(lat) * math.cos(lon), (n_m + alt_m) * math.cos(lat) * math.sin(lon),
            (n_m * (1.0 - WGS84_E2) + alt_m) * math.sin(lat))


def distance_m(a: dict, b: dict) -> float | None:
    """Straight-line distance between two positions {lat_deg, lon_deg, alt_m}; None when either is unknown."""
    try:
        d = math.dist(ecef_m(a["lat_deg"], a["lon_deg"], a["alt_m"]), ecef_m(b["lat_deg"], b["lon_deg"], b["alt_m"]))
    except (KeyError, TypeError, ValueError, OverflowError):
        return None
    return d if math.isfinite(d) else None


def ecef_to_lla(xyz):
    xyz = np.asarray(xyz, dtype=float)
    x, y, z = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    lat = np.arctan2(z, p * (1.0 - WGS84_E2))
    for _ in range(5):  # converges to < 1e-12 rad in 3 iterations at flight altitudes
        sin_lat = np.sin(lat)
        n_m = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
        alt = p / np.cos(lat) - n_m
        lat = np.arctan2(z, p * (1.0 - WGS84_E2 * n_m / (n_m + alt)))
    sin_lat = np.sin(lat)
    n_m = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
    alt = p / np.cos(lat) - n_m
    return np.degrees(lat), np.degrees(lon), alt


def ecef_to_enu(points_ecef_m, home: Home):
    """ECEF points (..., 3) -> ENU metres about home, with up along home's normal (log analysis: tracks in metres)."""
    relative = np.asarray(points_ecef_m, dtype=float) - lla_to_ecef(home.lat_deg, home.lon_deg, home.alt_m)
    lat, lon = np.radians(home.lat_deg), np.radians(home.lon_deg)
    up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
    basis = np.vstack([_enu_basis(home.lat_deg, home.lon_deg), up])
    return relative @ basis.T


def _enu_basis(lat_deg, lon_deg) -> np.ndarray:
    """East and north unit vectors in ECEF, shape (..., 2, 3)."""
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    zero = np.zeros_like(lat)
    east = np.stack([-np.sin(lon), np.cos(lon), zero], axis=-1)
    north = np.stack([-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)], axis=-1)
    return np.stack([east, north], axis=-2)


def enu_to_lla_many(enu_m, lat0_deg, lon0_deg, alt0_m):
    """ENU metres (N, 3), each about its own home (arrays of N) -> (lat_deg, lon_deg, alt_m)."""
    enu_m = np.asarray(enu_m, dtype=float)
    lat0_deg, lon0_deg, alt0_m = (np.asarray(v, dtype=float) for v in (lat0_deg, lon0_deg, alt0_m))
    origin = lla_to_ecef(lat0_deg, lon0_deg, alt0_m)
    plane_point = origin + np.einsum("...k,...kj->...j", enu_m[..., :2], _enu_basis(lat0_deg, lon0_deg))
    lat, lon, _ = ecef_to_lla(plane_point)
    return lat, lon, alt0_m + enu_m[..., 2]


def enu_to_lla(enu_m, home: Home):
    """ENU metres (..., 3) about one home -> (lat_deg, lon_deg, alt_m) arrays."""
    enu_m = np.asarray(enu_m, dtype=float)
    shape = enu_m.shape[:-1]
    return enu_to_lla_many(enu_m, np.full(shape, home.lat_deg), np.full(shape, home.lon_deg),
                           np.full(shape, home.alt_m))


def lla_to_enu(lat_deg, lon_deg, alt_m, home: Home):
    """(lat_deg, lon_deg, alt_m) arrays -> ENU metres (..., 3)."""
    alt_m = np.asarray(alt_m, dtype=float)
    origin = lla_to_ecef(home.lat_deg, home.lon_deg, home.alt_m)
    at_home_height = lla_to_ecef(lat_deg, lon_deg, np.full_like(alt_m, home.alt_m))
    east_north = (at_home_height - origin) @ _enu_basis(home.lat_deg, home.lon_deg).T
    return np.concatenate([east_north, (alt_m - home.alt_m)[..., None]], axis=-1)


def offset_home(home: Home, east_m: float, north_m: float) -> Home:
    lat, lon, alt = enu_to_lla(np.array([east_m, north_m, 0.0]), home)
    return Home(float(lat), float(lon), float(alt))
