"""Distances between vehicles from their GPS positions (WGS-84, straight line through ECEF)."""

from __future__ import annotations

import math

import numpy as np

_A_M = 6378137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)


def ecef_m(lat_deg: float, lon_deg: float, alt_m: float) -> tuple[float, float, float]:
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n = _A_M / math.sqrt(1.0 - _E2 * math.sin(lat) ** 2)
    return ((n + alt_m) * math.cos(lat) * math.cos(lon), (n + alt_m) * math.cos(lat) * math.sin(lon),
            (n * (1.0 - _E2) + alt_m) * math.sin(lat))


def ecef_array_m(lat_deg, lon_deg, alt_m) -> np.ndarray:
    """ecef_m over arrays (log analysis): (..., 3) metres."""
    lat, lon = np.radians(np.asarray(lat_deg, float)), np.radians(np.asarray(lon_deg, float))
    alt = np.asarray(alt_m, float)
    n = _A_M / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack([(n + alt) * np.cos(lat) * np.cos(lon), (n + alt) * np.cos(lat) * np.sin(lon),
                     (n * (1.0 - _E2) + alt) * np.sin(lat)], axis=-1)


def distance_m(a: dict, b: dict) -> float | None:
    """Straight-line distance between two positions {lat_deg, lon_deg, alt_m}; None when either is unknown."""
    try:
        pa = ecef_m(a["lat_deg"], a["lon_deg"], a["alt_m"])
        pb = ecef_m(b["lat_deg"], b["lon_deg"], b["alt_m"])
    except (KeyError, TypeError):
        return None
    d = math.dist(pa, pb)
    return d if math.isfinite(d) else None
