"""Write the missions of the shipped scenarios (sitl/scenarios/*/): `python -m sitl.scenarios.generate`.

Every vehicle's home is its plan's planned home, all around one origin, so the geometry below is the whole
experiment. Vehicles hold (NAV_LOITER_TIME, an hour) at their last point: the runner ends the scenario at its
duration and lands them, so a mission never ends the experiment early.
"""

from __future__ import annotations

from pathlib import Path

from missions import Mission, PlannedHome
from missions.builder import Builder, offset
from missions.examples.generate import FLIGHT_TEST_ALT_M, FLIGHT_TEST_SPEED_MPS, PAPER_SIM_ALT_M
from missions.files import load_mission, save_mission

ORIGIN = PlannedHome(47.397742, 8.545594, 488.0)
HOLD_S = 3600.0
HERE = Path(__file__).resolve().parent


def at(east_m: float, north_m: float) -> PlannedHome:
    return offset(ORIGIN, east_m, north_m)


def hover(home: PlannedHome, alt_m: float) -> Mission:
    return Builder(home).takeoff(alt_m).hold(0.0, 0.0, alt_m, HOLD_S).land(0.0, 0.0).mission()


def route(home: PlannedHome, alt_m: float, points: list[tuple[float, float]],
          speed_mps: float | None = None) -> Mission:
    """Take off, fly through points (east, north from home), hold at the last one."""
    b = Builder(home).takeoff(alt_m)
    if speed_mps:
        b.speed(speed_mps)
    for east, north in points:
        b.waypoint(east, north, alt_m)
    east, north = points[-1]
    return b.hold(east, north, alt_m, HOLD_S).land(east, north).mission()


def paper_flight() -> dict[str, Mission]:
    """3 UAVs at 3.04 m. Moving: the master flies a 3 m leg north and holds; worker 1, 6 m east, flies 40 m north
    at 0.67 m/s and back, out of wifi-flight's ~22 m range from about 40 s to 90 s; worker 2, 6 m west, flies
    12 m north at the same speed and holds, always in range. Static: workers hover at 9.8 m and 8.9 m."""
    alt, v = FLIGHT_TEST_ALT_M, FLIGHT_TEST_SPEED_MPS
    return {
        "paper-flight-moving/master.plan": route(at(0, 0), alt, [(0.0, 3.0)], v),
        "paper-flight-moving/w1.plan": route(at(6, 0), alt, [(0.0, 40.0), (0.0, 0.0)], v),
        "paper-flight-moving/w2.plan": route(at(-6, 0), alt, [(0.0, 12.0)], v),
        "paper-flight-static/master.plan": hover(at(0, 0), alt),
        "paper-flight-static/w1.plan": hover(at(9.8, 0), alt),
        "paper-flight-static/w2.plan": hover(at(-8.9, 0), alt),
    }


def paper_sim() -> dict[str, Mission]:
    """4 UAVs at 10 m: static at 9.43, 12.80 and 17 m from the master; moving: the workers fly out to 30-40 m."""
    alt = PAPER_SIM_ALT_M
    homes = {"w1": at(9.43, 0), "w2": at(0, 12.8), "w3": at(-17.0, 0)}
    moving = {"w1": [(20.0, 15.0)], "w2": [(0.0, 25.0)], "w3": [(-20.0, -10.0)]}
    out = {"paper-sim-static/master.plan": hover(at(0, 0), alt),
           "paper-sim-moving/master.plan": route(at(0, 0), alt, [(0.0, 5.0)])}
    for worker, home in homes.items():
        out[f"paper-sim-static/{worker}.plan"] = hover(home, alt)
        out[f"paper-sim-moving/{worker}.plan"] = route(home, alt, moving[worker])
    return out


def range_sweep(step_m: float = 3.0, stops: int = 9, hold_s: float = 25.0) -> dict[str, Mission]:
    """2 UAVs at 3 m: the worker starts 2 m from the hovering master and steps away, holding at each distance."""
    alt = 3.0
    b = Builder(at(2.0, 0)).takeoff(alt)
    for k in range(stops):
        b.hold(k * step_m, 0.0, alt, hold_s)
    b.land((stops - 1) * step_m, 0.0)
    return {"range-sweep/master.plan": hover(at(0, 0), alt), "range-sweep/worker.plan": b.mission()}


def coded_edge() -> dict[str, Mission]:
    """5 UAVs at 3.04 m for the coded-computing pair: workers 1 and 2 hover 8 m east and west of the master; worker
    3 flies from 8 m north to 20 m north at 0.67 m/s and holds there, near the edge of wifi-flight's ~22-25 m
    range, where its rate is low and its frames fail and are retried; worker 4 hovers 8 m south (the scenarios give
    it a slow companion)."""
    alt, v = FLIGHT_TEST_ALT_M, FLIGHT_TEST_SPEED_MPS
    return {"coded-edge/master.plan": hover(at(0, 0), alt), "coded-edge/w1.plan": hover(at(8, 0), alt),
            "coded-edge/w2.plan": hover(at(-8, 0), alt),
            "coded-edge/w3.plan": route(at(0, 8), alt, [(0.0, 12.0)], v), "coded-edge/w4.plan": hover(at(0, -8), alt)}


def energy_short() -> dict[str, Mission]:
    """4 UAVs at 3.04 m for the energy pair: the workers hover 8 m east, west and north of the master."""
    alt = FLIGHT_TEST_ALT_M
    return {"energy-short/master.plan": hover(at(0, 0), alt), "energy-short/w1.plan": hover(at(8, 0), alt),
            "energy-short/w2.plan": hover(at(-8, 0), alt), "energy-short/w3.plan": hover(at(0, 8), alt)}


def write_all(out_dir: Path = HERE) -> list[Path]:
    paths = []
    for name, mission in {**paper_flight(), **paper_sim(), **range_sweep(), **coded_edge(), **energy_short()}.items():
        path = out_dir / name
        path.parent.mkdir(parents=True, exist_ok=True)
        save_mission(mission, path)
        if not load_mission(path).same_items_as(mission):
            raise RuntimeError(f"{path}: did not read back item for item")
        paths.append(path)
    return paths


if __name__ == "__main__":
    for written in write_all():
        print(f"wrote {written}")
