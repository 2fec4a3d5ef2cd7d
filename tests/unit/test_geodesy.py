import math

import numpy as np
import pytest

from missions.geo import WGS84_A_M, WGS84_F, Home, enu_to_lla, lla_to_enu, offset_home


def vincenty_distance_m(lat1, lon1, lat2, lon2):
    """Independent reference: Vincenty's inverse formula on WGS-84."""
    a, f = WGS84_A_M, WGS84_F
    b = a * (1 - f)
    u1 = math.atan((1 - f) * math.tan(math.radians(lat1)))
    u2 = math.atan((1 - f) * math.tan(math.radians(lat2)))
    big_l = math.radians(lon2 - lon1)
    lam = big_l
    for _ in range(200):
        sin_sigma = math.hypot(math.cos(u2) * math.sin(lam),
                               math.cos(u1) * math.sin(u2) - math.sin(u1) * math.cos(u2) * math.cos(lam))
        cos_sigma = math.sin(u1) * math.sin(u2) + math.cos(u1) * math.cos(u2) * math.cos(lam)
        sigma = math.atan2(sin_sigma, cos_sigma)
        sin_alpha = math.cos(u1) * math.cos(u2) * math.sin(lam) / sin_sigma
        cos2_alpha = 1 - sin_alpha**2
        cos_2sm = cos_sigma - 2 * math.sin(u1) * math.sin(u2) / cos2_alpha
        c = f / 16 * cos2_alpha * (4 + f * (4 - 3 * cos2_alpha))
        lam_prev = lam
        lam = big_l + (1 - c) * f * sin_alpha * (
            sigma + c * sin_sigma * (cos_2sm + c * cos_sigma * (-1 + 2 * cos_2sm**2)))
        if abs(lam - lam_prev) < 1e-13:
            break
    u_sq = cos2_alpha * (a**2 - b**2) / b**2
    big_a = 1 + u_sq / 16384 * (4096 + u_sq * (-768 + u_sq * (320 - 175 * u_sq)))
    big_b = u_sq / 1024 * (256 + u_sq * (-128 + u_sq * (74 - 47 * u_sq)))
    d_sigma = big_b * sin_sigma * (cos_2sm + big_b / 4 * (
        cos_sigma * (-1 + 2 * cos_2sm**2) - big_b / 6 * cos_2sm * (-3 + 4 * sin_sigma**2) * (-3 + 4 * cos_2sm**2)))
    return b * big_a * (sigma - d_sigma)


HOMES = [Home(47.397742, 8.545594, 488.0), Home(-35.363261, 149.165230, 584.0), Home(0.5, -70.0, 10.0)]


@pytest.mark.parametrize("home", HOMES)
def test_round_trip_within_5km_is_exact_to_a_centimetre(home):
    rng = np.random.default_rng(1)
    enu = np.column_stack([rng.uniform(-3500, 3500, 500), rng.uniform(-3500, 3500, 500), rng.uniform(0, 120, 500)])
    lat, lon, alt = enu_to_lla(enu, home)
    back = lla_to_enu(lat, lon, alt, home)
    assert np.max(np.abs(back - enu)) < 0.01


@pytest.mark.parametrize("home", HOMES)
@pytest.mark.parametrize("bearing_deg", [0, 45, 90, 200, 315])
def test_distance_from_home_matches_vincenty_within_0_1_m(home, bearing_deg):
    for dist_m in (10.0, 500.0, 5000.0):
        b = math.radians(bearing_deg)
        lat, lon, _ = enu_to_lla(np.array([dist_m * math.sin(b), dist_m * math.cos(b), 0.0]), home)
        # Vincenty measures on the ellipsoid; the local frame sits at home's altitude, a little farther out.
        ref = vincenty_distance_m(home.lat_deg, home.lon_deg, float(lat), float(lon)) * (1 + home.alt_m / 6371000)
        assert abs(ref - dist_m) < 0.1, (dist_m, ref)


def test_north_is_north_and_east_is_east():
    home = HOMES[0]
    lat, lon, alt = enu_to_lla(np.array([0.0, 100.0, 5.0]), home)
    assert lat > home.lat_deg and abs(lon - home.lon_deg) < 1e-9 and alt == pytest.approx(home.alt_m + 5)
    lat, lon, _ = enu_to_lla(np.array([100.0, 0.0, 0.0]), home)
    assert lon > home.lon_deg and abs(lat - home.lat_deg) < 1e-6


def test_offset_home_places_vehicles_apart():
    home = HOMES[0]
    other = offset_home(home, 10.0, 0.0)
    assert vincenty_distance_m(home.lat_deg, home.lon_deg, other.lat_deg, other.lon_deg) == pytest.approx(10, abs=1e-3)

