"""SMART_RTL's trail (sitl.vehicle.smart_rtl): simplified as AP_SmartRTL simplifies it."""

import numpy as np

from sitl.vehicle.smart_rtl import simplify


def test_an_l_shaped_trail_with_wobbles_within_the_accuracy_simplifies_to_its_corner_and_ends():
    rng = np.random.default_rng(7)
    north = np.column_stack([np.zeros(16), np.arange(0, 32, 2.0), np.full(16, 10.0)])
    east = np.column_stack([np.arange(2, 32, 2.0), np.full(15, 30.0), np.full(15, 10.0)])
    trail = np.vstack([north, east])
    trail[1:-1, :2] += rng.uniform(-0.5, 0.5, (len(trail) - 2, 2))
    kept = simplify(trail, 2.0)
    assert len(kept) == 3 and np.allclose(kept[[0, -1]], trail[[0, -1]])
    assert np.hypot(*(kept[1, :2] - [0.0, 30.0])) < 1.0, "the corner stays"


def test_a_straight_trail_keeps_its_ends_and_a_single_point_is_itself():
    line = np.column_stack([np.linspace(0, 50, 26), np.zeros(26), np.full(26, 5.0)])
    assert np.allclose(simplify(line, 0.5), line[[0, -1]])
    assert np.allclose(simplify(line[:1], 0.5), line[:1])
