"""A minimal ground station over pymavlink for driving the SITL in tests (the product client comes later)."""

from __future__ import annotations

import os
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from missions.model import Frame, MavCmd, MissionItem  # noqa: E402

M = mavutil.mavlink


class Gcs:
    def __init__(self, port: int, sysid: int = 1, source_system: int = 255):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=source_system,
                                               source_component=M.MAV_COMP_ID_MISSIONPLANNER)
        self.sysid = sysid
        self.seen: list = []  # every message received, in order

    def close(self) -> None:
        self.conn.close()

    def recv(self, types, timeout_s: float, predicate=lambda m: True):
        deadline = time.monotonic() + timeout_s
        types = [types] if isinstance(types, str) else types
        while time.monotonic() < deadline:
            msg = self.conn.recv_match(blocking=True, timeout=min(0.2, max(deadline - time.monotonic(), 0.01)))
            if msg is None:
                continue
            self.seen.append(msg)
            if msg.get_srcSystem() != self.sysid and msg.get_type() != "BAD_DATA":
                continue
            if msg.get_type() in types and predicate(msg):
                return msg
        return None

    def wait_heartbeat(self, timeout_s: float = 5.0):
        hb = self.recv("HEARTBEAT", timeout_s)
        assert hb is not None, "no heartbeat from the SITL"
        self.conn.target_system, self.conn.target_component = self.sysid, 1
        return hb

    def command(self, command: int, *params: float, timeout_s: float = 3.0, retries: int = 3) -> int:
        p = list(params) + [0.0] * (7 - len(params))
        for confirmation in range(retries):
            self.conn.mav.command_long_send(self.sysid, 1, command, confirmation, *p)
            ack = self.recv("COMMAND_ACK", timeout_s, lambda m: m.command == command)
            if ack is not None:
                return ack.result
        raise TimeoutError(f"no COMMAND_ACK for command {command}")

    def set_mode(self, name: str) -> int:
        mode = {v: k for k, v in mavutil.mode_mapping_acm.items()}[name]
        return self.command(MavCmd.DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)

    def upload(self, items: list[MissionItem], mission_type: int = 0, timeout_s: float = 60.0,
               item_timeout_s: float = 1.5):
        """Upload with the spec's client behaviour: resend COUNT or the last item when the vehicle goes quiet."""
        mav = self.conn.mav
        deadline = time.monotonic() + timeout_s
        mav.mission_count_send(self.sysid, 1, len(items), mission_type)
        last_sent = None
        while time.monotonic() < deadline:
            msg = self.recv(["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], item_timeout_s,
                            lambda m: m.mission_type == mission_type)
            if msg is None:
                if last_sent is None:
                    mav.mission_count_send(self.sysid, 1, len(items), mission_type)
                else:
                    self._send_item(items[last_sent], mission_type)
                continue
            if msg.get_type() == "MISSION_ACK":
                return msg.type
            last_sent = msg.seq
            self._send_item(items[msg.seq], mission_type)
        raise TimeoutError("mission upload timed out")

    def _send_item(self, it: MissionItem, mission_type: int) -> None:
        self.conn.mav.mission_item_int_send(
            self.sysid, 1, it.seq, it.frame, it.command, 0, int(it.autocontinue), it.p1, it.p2, it.p3, it.p4,
            int(round(it.lat_deg * 1e7)), int(round(it.lon_deg * 1e7)), it.alt_m, mission_type)

    def download(self, mission_type: int = 0, timeout_s: float = 30.0) -> list[MissionItem]:
        mav = self.conn.mav
        deadline = time.monotonic() + timeout_s
        count = None
        while count is None and time.monotonic() < deadline:
            mav.mission_request_list_send(self.sysid, 1, mission_type)
            msg = self.recv("MISSION_COUNT", 1.5, lambda m: m.mission_type == mission_type)
            count = None if msg is None else msg.count
        items: list[MissionItem] = []
        while count is not None and len(items) < count and time.monotonic() < deadline:
            mav.mission_request_int_send(self.sysid, 1, len(items), mission_type)
            msg = self.recv("MISSION_ITEM_INT", 0.5, lambda m: m.seq == len(items))
            if msg is not None:
                items.append(MissionItem(msg.seq, msg.command, msg.frame, msg.param1, msg.param2, msg.param3,
                                         msg.param4, msg.x / 1e7, msg.y / 1e7, msg.z, bool(msg.autocontinue),
                                         mission_type=msg.mission_type))
        if count is None or len(items) < count:
            raise TimeoutError("mission download timed out")
        mav.mission_ack_send(self.sysid, 1, M.MAV_MISSION_ACCEPTED, mission_type)
        return items


def waypoint_mission(home_lat: float, home_lon: float, offsets_m: list[tuple[float, float]], alt_m: float = 10.0,
                     land: bool = True) -> list[MissionItem]:
    """Home placeholder, takeoff, one waypoint per (east, north) offset, then land."""
    from sitl.geodesy import Home, offset_home

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
