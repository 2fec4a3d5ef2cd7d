"""ArduCopter's SMART_RTL (pure): the way back the vehicle came, then a landing where it took off.

While armed and flying (and not already returning) every vehicle leaves a breadcrumb each SRTL_ACCURACY metres
(ArduCopter's AP_SmartRTL). Entering SMART_RTL simplifies the trail (Ramer-Douglas-Peucker: points within
SRTL_ACCURACY of the line between their neighbours go, as AP_SmartRTL's simplification does) and flies it backwards,
point to point, to the first breadcrumb (where it armed), then lands there. A trail longer than SRTL_POINTS keeps
every other point (AP_SmartRTL prunes loops and simplifies instead; the ends are the same). Without a trail (armed
in flight, or the trail lost) it returns as RTL does, as ArduCopter falls back.
"""

from __future__ import annotations

import numpy as np

from sitl.vehicle.flight_state import Check, CopterMode, FlightState, Phase, Severity
from sitl.vehicle.physics import Motion, VehicleState

MIN_ALT_M = 2.0  # the way back stays this high until the landing: the first breadcrumb is on the ground
RECORD_PERIOD_S = 0.1  # simulated: at 20 m/s a 2 m breadcrumb spacing is one look per 0.1 s (not every step)


def start_trail(s: FlightState, i: int) -> None:
    """On arming: the trail starts where the vehicle is."""
    s.trail_m[i] = [s.pos(i)]
    s.trail_last_m[i] = s.trail_m[i][0]


def record(s: FlightState, state: VehicleState) -> None:
    """A breadcrumb for each flying vehicle that has moved SRTL_ACCURACY from its last one (vectorised test)."""
    flying = s.armed & ~state.on_ground & (s.mode != CopterMode.SMART_RTL)
    moved_m = np.linalg.norm(state.pos_m - s.trail_last_m, axis=1)
    for i in np.flatnonzero(flying & (moved_m >= s.params.column("SRTL_ACCURACY"))):
        trail = s.trail_m[i]
        trail.append(state.pos_m[i].copy())
        s.trail_last_m[i] = trail[-1]
        if len(trail) > max(int(s.params.get(i, "SRTL_POINTS")), 2):
            del trail[1:-1:2]


def begin(s: FlightState, i: int) -> bool:
    """SMART_RTL entered: fly the simplified trail backwards (on the ground: hold). False when there is no trail:
    the caller falls back to RTL, as ArduCopter does."""
    if not s.flying(i):
        s.hold(i)
        return True
    trail = s.trail_m[i]
    if len(trail) < 1:
        s.text(i, "SmartRTL unavailable, using RTL", Severity.WARNING)
        return False
    way_back = simplify(np.array([*trail, s.pos(i)]), max(s.params.get(i, "SRTL_ACCURACY"), 0.1))[::-1][1:]
    way_back[:, 2] = np.maximum(way_back[:, 2], MIN_ALT_M)
    s.srtl_route[i] = list(way_back)
    next_point(s, i)
    return True


def next_point(s: FlightState, i: int) -> None:
    """The next breadcrumb back, or, past the last, the landing."""
    route = s.srtl_route.get(i)
    if not route:
        s.srtl_route.pop(i, None)
        here = s.pos(i)
        s.set_goal(i, [here[0], here[1], 0.0], Motion.LAND, Check.LANDED, phase=Phase.LAND)
        return
    s.set_goal(i, route.pop(0), Motion.GOTO, Check.REACH, s.wp_radius_m(i), Phase.SMART_RTL)


def simplify(points: np.ndarray, epsilon_m: float) -> np.ndarray:
    """Ramer-Douglas-Peucker: the points that keep the polyline within epsilon_m of the original (ends kept)."""
    keep = np.zeros(len(points), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(points) - 1)]
    while stack:
        first, last = stack.pop()
        if last - first < 2:
            continue
        a, b = points[first], points[last]
        inner = points[first + 1:last]
        ab = b - a
        length = float(np.linalg.norm(ab))
        if length < 1e-9:
            distances = np.linalg.norm(inner - a, axis=1)
        else:
            t = np.clip((inner - a) @ ab / length ** 2, 0.0, 1.0)
            distances = np.linalg.norm(inner - (a + t[:, None] * ab), axis=1)
        k = int(np.argmax(distances))
        if distances[k] > epsilon_m:
            keep[first + 1 + k] = True
            stack += [(first, first + 1 + k), (first + 1 + k, last)]
    return points[keep]
