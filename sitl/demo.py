"""`make demo` for now: a SITL flight of several vehicles, each flown through its own mission by the MAVLink
client exactly as a companion computer would (upload, arm, start, watch), printing their progress.

    python -m sitl.demo [--vehicles 4] [--speedup 10]
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from dataclasses import dataclass, field

from missions.model import Frame, MavCmd, MissionItem
from nac_onboard.mavlink_client import COPTER_MODES, M, VehicleClient
from sitl.geodesy import Home, offset_home
from sitl.server import Sitl, SitlConfig

MODE_NAMES = {number: name for name, number in COPTER_MODES.items()}


def waypoint_mission(home_lat: float, home_lon: float, offsets_m: list[tuple[float, float]], alt_m: float = 10.0,
                     land: bool = True) -> list[MissionItem]:
    """Home slot, takeoff, one waypoint per (east, north) offset from home in metres, then land."""
    home = Home(home_lat, home_lon, 0.0)
    items = [MissionItem(0, MavCmd.NAV_WAYPOINT, Frame.GLOBAL, lat_deg=home_lat, lon_deg=home_lon),
             MissionItem(1, MavCmd.NAV_TAKEOFF, Frame.GLOBAL_RELATIVE_ALT_INT, alt_m=alt_m)]
    for east, north in offsets_m:
        wp = offset_home(home, east, north)
        items.append(MissionItem(len(items), MavCmd.NAV_WAYPOINT, Frame.GLOBAL_RELATIVE_ALT_INT,
                                 lat_deg=wp.lat_deg, lon_deg=wp.lon_deg, alt_m=alt_m))
    if land:
        items.append(MissionItem(len(items), MavCmd.NAV_LAND, Frame.GLOBAL_RELATIVE_ALT_INT))
    return items


def square_legs(vehicle: int, side_m: float = 20.0) -> list[tuple[float, float]]:
    """A square, rotated per vehicle so the fleet fans out."""
    angle = vehicle * math.pi / 4
    corners = [(side_m, 0.0), (side_m, side_m), (0.0, side_m), (0.0, 0.0)]
    return [(x * math.cos(angle) - y * math.sin(angle), x * math.sin(angle) + y * math.cos(angle)) for x, y in corners]


@dataclass
class Progress:
    mode: str = "?"
    armed: bool = False
    rel_alt_m: float = 0.0
    speed_mps: float = 0.0
    item: int = 0
    total: int = 0
    reached: list[int] = field(default_factory=list)
    landed: bool = False
    error: str = ""


def fly(client: VehicleClient, items: list[MissionItem], progress: Progress, stop: threading.Event) -> None:
    """Upload, arm, start and follow one vehicle until it has landed and disarmed."""
    try:
        client.wait_heartbeat(10.0)
        result = client.upload(items)
        if result != M.MAV_MISSION_ACCEPTED:
            progress.error = f"upload refused ({result})"
            return
        progress.total = len(items) - 1
        client.command_ok(MavCmd.COMPONENT_ARM_DISARM, 1)
        client.command_ok(MavCmd.MISSION_START, 0, 0)
        flown = False
        while not stop.is_set():
            msg = client.recv(["HEARTBEAT", "GLOBAL_POSITION_INT", "MISSION_ITEM_REACHED", "MISSION_CURRENT"], 5.0)
            if msg is None:
                progress.error = "link silent for 5 s"
                return
            kind = msg.get_type()
            if kind == "HEARTBEAT":
                progress.mode = MODE_NAMES.get(msg.custom_mode, str(msg.custom_mode))
                progress.armed = bool(msg.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
                flown |= progress.armed
                if flown and not progress.armed and progress.reached[-1:] == [progress.total]:
                    progress.landed = True
                    return
            elif kind == "GLOBAL_POSITION_INT":
                progress.rel_alt_m = msg.relative_alt / 1000
                progress.speed_mps = math.hypot(msg.vx, msg.vy) / 100
            elif kind == "MISSION_ITEM_REACHED":
                progress.reached.append(msg.seq)
            else:
                progress.item = msg.seq
    except Exception as err:  # shown in the table and the exit code, never a traceback
        progress.error = str(err)


def run_demo(vehicles: int, speedup: float, base_port: int, out=sys.stdout, timeout_s: float = 300.0) -> int:
    config = SitlConfig(vehicles=vehicles, speedup=speedup, spacing_m=10.0, gcs_base_port=base_port,
                        companion_base_port=base_port + 1, tcp_base_port=0)
    print(f"NAC demo: {vehicles} simulated quadcopters at {speedup:g}x real time. Ground stations can watch on "
          f"udpin:0.0.0.0:{base_port} (+10 per vehicle); this script flies them over the companion links.",
          file=out, flush=True)
    stop = threading.Event()
    with Sitl(config) as sim:
        states = [Progress() for _ in range(vehicles)]
        clients, threads = [], []
        for i in range(vehicles):
            client = VehicleClient(f"udpin:127.0.0.1:{config.companion_base_port + 10 * i}", sysid=i + 1)
            home = sim.homes[i]
            items = waypoint_mission(home.lat_deg, home.lon_deg, square_legs(i), alt_m=8.0 + 2 * i)
            thread = threading.Thread(target=fly, args=(client, items, states[i], stop), daemon=True)
            clients.append(client)
            threads.append(thread)
            thread.start()
        deadline = time.monotonic() + timeout_s
        try:
            while any(t.is_alive() for t in threads) and time.monotonic() < deadline:
                time.sleep(1.0)  # the display refresh period, not a wait for the simulation
                print(format_row(sim.t_s, states), file=out, flush=True)
        finally:
            stop.set()
            for t in threads:
                t.join(6.0)
            for client in clients:
                client.close()
        failed = [i + 1 for i, s in enumerate(states) if not s.landed]
        for i, s in enumerate(states):
            verdict = "landed, mission complete" if s.landed else f"FAILED: {s.error or 'did not finish'}"
            print(f"vehicle {i + 1}: items reached {s.reached} -> {verdict}", file=out)
        print(f"simulated {sim.t_s:.0f} s; {vehicles - len(failed)}/{vehicles} vehicles completed their missions",
              file=out, flush=True)
    return 1 if failed else 0


def format_row(t_s: float, states: list[Progress]) -> str:
    cells = [f"V{i + 1} {s.mode:<9}{'A' if s.armed else '-'} alt {s.rel_alt_m:5.1f} m {s.speed_mps:4.1f} m/s "
             f"item {s.item}/{s.total}" for i, s in enumerate(states)]
    return f"t={t_s:6.1f}s | " + " | ".join(cells)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sitl.demo", description=__doc__)
    parser.add_argument("--vehicles", type=int, default=4)
    parser.add_argument("--speedup", type=float, default=10.0)
    parser.add_argument("--base-port", type=int, default=14550)
    args = parser.parse_args(argv)
    if not 1 <= args.vehicles <= 20:
        print("python -m sitl.demo: --vehicles must be 1..20", file=sys.stderr)
        return 2
    return run_demo(args.vehicles, args.speedup, args.base_port)


if __name__ == "__main__":
    sys.exit(main())
