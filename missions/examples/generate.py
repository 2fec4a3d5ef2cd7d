"""Write the example missions with the library's own writer, so they are exactly what it reads back.

    python -m missions.examples.generate        (from the repository root)

Geometry assumes the SITL defaults: home 47.397742, 8.545594, 488 m AMSL and `nac-sitl run --spacing-m 5`, so
vehicle i (0-based) starts 5*i m east of that home. Vehicle 1 (i = 0) is the master in both scenarios. Every
mission takes off where the vehicle stands and lands at its last point, so `nac-ground wait landed` finishes.
"""

from __future__ import annotations

from pathlib import Path

from missions import Mission, PlannedHome, load_mission, save_mission
from missions.builder import Builder, offset
from missions.geo import distance_m

SITL_HOME = PlannedHome(47.397742, 8.545594, 488.0)
SPACING_M = 5.0
MAX_RANGE_M = 300.0  # every point stays this close to the flying vehicle's home
HERE = Path(__file__).resolve().parent

PAPER_SIM_ALT_M = 10.0
FLIGHT_TEST_ALT_M = 3.04  # the paper's flight-test altitude (10 ft)
FLIGHT_TEST_SPEED_MPS = 0.67  # the paper's flight-test ground speed (1.5 mph)
FLIGHT_TEST_HOLD_S = 60.0




def vehicle_home(i: int) -> PlannedHome:
    return offset(SITL_HOME, SPACING_M * i, 0.0)




def leg(home: PlannedHome, alt_m: float, east_m: float, north_m: float) -> Mission:
    """Take off, fly one straight leg to (east_m, north_m) from home, land there."""
    return Builder(home).takeoff(alt_m).waypoint(east_m, north_m, alt_m).land(east_m, north_m).mission()


def paper_sim() -> dict[str, Mission]:
    """Matrix-multiplication scenario, 1 master + 3 workers: the master shifts 10 m north while the workers fly
    30-40 m away from it, fanning out east so the master-worker links weaken through the run."""
    alt = PAPER_SIM_ALT_M
    return {
        "paper-sim-master.plan": leg(vehicle_home(0), alt, 0.0, 10.0),
        "paper-sim-worker1.plan": leg(vehicle_home(1), alt, 26.0, 15.0),  # 30 m towards east-north-east
        "paper-sim-worker2.plan": leg(vehicle_home(2), alt, 35.0, 0.0),  # 35 m east
        "paper-sim-worker3.plan": leg(vehicle_home(3), alt, 34.6, -20.0),  # 40 m towards east-south-east
    }


def flight_test() -> dict[str, Mission]:
    """Linear-regression flight test, 1 master + 2 workers: the workers fly parallel 40 m lines north at
    0.67 m/s and 3.04 m; the master moves 5 m north, holds there 60 s and lands."""
    alt, v = FLIGHT_TEST_ALT_M, FLIGHT_TEST_SPEED_MPS

    def worker(i: int) -> Mission:
        home = vehicle_home(i)
        return Builder(home).takeoff(alt).speed(v).waypoint(0.0, 40.0, alt).land(0.0, 40.0).mission()

    master = (Builder(vehicle_home(0)).takeoff(alt).waypoint(0.0, 5.0, alt).hold(0.0, 5.0, alt, FLIGHT_TEST_HOLD_S)
              .land(0.0, 5.0).mission())
    return {"flight-test-master.plan": master, "flight-test-worker1.plan": worker(1),
            "flight-test-worker2.plan": worker(2)}




def examples() -> dict[str, Mission]:
    """File name -> mission, for every example."""
    return {**paper_sim(), **flight_test()}


def write_examples(out_dir: Path = HERE) -> list[Path]:
    """Write every example to out_dir, read each back (validating it) and check it stays near its home."""
    paths = []
    for name, mission in examples().items():
        path = Path(out_dir) / name
        save_mission(mission, path)
        back = load_mission(path)
        if not back.same_items_as(mission):
            raise RuntimeError(f"{path}: did not read back item for item")
        for item in back.items:
            point = {"lat_deg": item.lat_deg, "lon_deg": item.lon_deg, "alt_m": back.home.alt_m}
            far_m = distance_m(vars(back.home), point) if item.lat_deg else 0.0
            if far_m > MAX_RANGE_M:
                raise RuntimeError(f"{path}: item {item.seq} is {far_m:.0f} m from home (limit {MAX_RANGE_M:g} m)")
        paths.append(path)
    return paths


def main() -> None:
    for path in write_examples():
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
