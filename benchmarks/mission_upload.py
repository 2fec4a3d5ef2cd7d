"""Mission upload time: NAC's client against MAVSDK's mission_raw, same SITL, same missions, same run.

10, 100 and 500 items; on loopback and with 10 % and 30 % injected loss (both directions, SIM_LOSS_GCS and
SIM_LOSS_CC). The SITL runs as its own process (`nac-sitl run`); NAC's client uploads over the ground link,
MAVSDK over the companion link. Each cell is the median of --repeats uploads.

    python benchmarks/mission_upload.py [--repeats 3] [--sizes 10 100 500] [--losses 0 10 30] [--smoke]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import threading
import time

from missions.builder import waypoint_mission
from missions.geo import Home
from nac_onboard.mavlink.client import M, VehicleClient
from sitl.launcher import SitlProcess, allocate_base_port
from sitl.server import SitlConfig

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

HOME = Home(47.397742, 8.545594, 488.0)
SMOKE = {"repeats": 1, "sizes": [10], "losses": [0.0, 10.0]}  # --smoke: one loopback cell and one lossy cell


def mission(n_items: int):
    offsets = [(float(k % 20) * 2, float(k // 20) * 2) for k in range(n_items - 3)]
    return waypoint_mission(HOME.lat_deg, HOME.lon_deg, offsets)


def set_loss(client: VehicleClient, pct: float) -> None:
    for name in ("SIM_LOSS_GCS", "SIM_LOSS_CC"):
        for _ in range(20):  # the set itself crosses the lossy link
            client.conn.mav.param_set_send(1, 1, name.encode(), pct, M.MAV_PARAM_TYPE_REAL32)
            echo = client.recv("PARAM_VALUE", 0.5, lambda m, n=name: m.param_id == n)
            if echo is not None and abs(echo.param_value - pct) < 1e-3:
                break


def nac_upload_s(client: VehicleClient, items) -> float:
    for _ in range(20):
        start = time.perf_counter()
        result = client.upload(items)
        elapsed = time.perf_counter() - start
        if result == M.MAV_MISSION_ACCEPTED:
            return elapsed
        if result != M.MAV_MISSION_DENIED:
            raise RuntimeError(f"NAC upload refused: {result}")
        # DENIED: a transfer MAVSDK abandoned still holds the vehicle until its 8 s idle timeout
        client.recv("HEARTBEAT", 1.0)
    raise RuntimeError("vehicle stayed busy with another transfer")


class Mavsdk:
    def __init__(self, port: int):
        from mavsdk import ComponentType, Configuration, Mavsdk, log_subscribe
        from mavsdk.plugins.mission_raw import MissionRaw

        log_subscribe(lambda *args: True)
        self.config = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
        self.client = Mavsdk(self.config)
        self.client.add_any_connection(f"udpin://0.0.0.0:{port}")
        system = self.client.first_autopilot(10.0)
        if system is None:
            raise RuntimeError("MAVSDK found no vehicle")
        self.mission = MissionRaw(system)

    def upload_s(self, items) -> float:
        from mavsdk.plugins.mission_raw import MissionItem

        raw = [MissionItem(seq=it.seq, frame=it.frame, command=it.command, current=int(it.seq == 0), autocontinue=1,
                           param1=it.p1, param2=it.p2, param3=it.p3, param4=it.p4,
                           x=int(round(it.lat_deg * 1e7)), y=int(round(it.lon_deg * 1e7)), z=it.alt_m,
                           mission_type=0) for it in items]
        done, box = threading.Event(), {}
        start = time.perf_counter()
        self.mission.upload_mission_async(raw, lambda result, _ud: (box.setdefault("r", result), done.set()))
        if not done.wait(300):
            raise RuntimeError("MAVSDK upload did not finish in 300 s")
        elapsed = time.perf_counter() - start
        if box["r"].name != "SUCCESS":
            print(f"MAVSDK upload: {box['r'].name}", file=sys.stderr)
            return float("nan")  # MAVSDK gave up: shown as nan
        return elapsed

    def close(self):
        self.client.destroy()
        self.config.destroy()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 500])
    parser.add_argument("--losses", type=float, nargs="+", default=[0.0, 10.0, 30.0])
    parser.add_argument("--base-port", type=int, default=None, help="ground link's UDP port (default: a free one)")
    args = _common.parse_args(parser, SMOKE)
    base = args.base_port or allocate_base_port(1)
    config = SitlConfig(vehicles=1, gcs_base_port=base, companion_base_port=base + 1, tcp_base_port=0)
    print("| items | loss | NAC client (s) | MAVSDK mission_raw (s) |")
    print("| ---: | ---: | ---: | ---: |")
    with SitlProcess(config):
        nac = VehicleClient(f"udpin:127.0.0.1:{base}", sysid=1)
        nac.wait_heartbeat(10)
        sdk = Mavsdk(base + 1)
        try:
            for loss in args.losses:
                set_loss(nac, loss)
                for n in args.sizes:
                    items = mission(n)
                    ours = statistics.median(nac_upload_s(nac, items) for _ in range(args.repeats))
                    theirs = statistics.median(sdk.upload_s(items) for _ in range(args.repeats))
                    print(f"| {n} | {loss:g} % | {ours:.3f} | {theirs:.3f} |", flush=True)
        finally:
            sdk.close()
            nac.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
