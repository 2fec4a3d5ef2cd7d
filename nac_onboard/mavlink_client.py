"""MAVLink client used by the ground station, the agent and the demo (the one module here importing pymavlink).

Endpoints are URIs: udpin:HOST:PORT (listen, as QGroundControl does), udpout:HOST:PORT (send first),
tcp:HOST:PORT, serial:DEVICE:BAUD. The environment variable NAC_MAVLINK_URI overrides the default.
"""

from __future__ import annotations

import logging
import os
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from missions.model import MavCmd, MissionItem  # noqa: E402

log = logging.getLogger(__name__)
M = mavutil.mavlink
DEFAULT_URI = "udpin:0.0.0.0:14550"
COPTER_MODES = {name: number for number, name in mavutil.mode_mapping_acm.items()}


class LinkError(RuntimeError):
    """The link could not be opened or stayed silent; the message says which endpoint and what was expected."""


class CommandError(RuntimeError):
    def __init__(self, command: int, result: int):
        self.command, self.result = command, result
        name = M.enums["MAV_RESULT"][result].name if result in M.enums["MAV_RESULT"] else str(result)
        super().__init__(f"command {command} refused by the vehicle: {name}")


class MissionError(RuntimeError):
    def __init__(self, what: str, result: int | None = None):
        self.result = result
        if result is not None and result in M.enums["MAV_MISSION_RESULT"]:
            what += f": {M.enums['MAV_MISSION_RESULT'][result].name}"
        super().__init__(what)


def mavutil_device(uri: str) -> tuple[str, dict]:
    """Map a NAC endpoint URI to pymavlink's device string and options."""
    scheme, _, rest = uri.partition(":")
    if scheme in ("udpin", "udpout", "tcp", "tcpin") and rest.rpartition(":")[2].isdigit():
        return uri, {}
    if scheme == "serial":
        device, _, baud = rest.rpartition(":")
        if device and baud.isdigit():
            return device, {"baud": int(baud)}
    raise LinkError(f"endpoint {uri!r} not understood: expected udpin:HOST:PORT, udpout:HOST:PORT, "
                    f"tcp:HOST:PORT or serial:DEVICE:BAUD")


class VehicleClient:
    """Talks to one vehicle (by sysid) over one link."""

    def __init__(self, uri: str | None = None, sysid: int = 1, source_system: int = 255,
                 source_component: int = M.MAV_COMP_ID_MISSIONPLANNER):
        self.uri = uri or os.environ.get("NAC_MAVLINK_URI", DEFAULT_URI)
        device, options = mavutil_device(self.uri)
        try:
            self.conn = mavutil.mavlink_connection(device, source_system=source_system,
                                                   source_component=source_component, **options)
        except OSError as err:
            raise LinkError(f"cannot open {self.uri}: {err.strerror or err}") from None
        self.sysid = sysid
        self.seen: list = []  # every message received, in order (handy for tools and tests)

    def close(self) -> None:
        self.conn.close()

    def recv(self, types, timeout_s: float, predicate=lambda m: True):
        """The next message of `types` from our vehicle matching predicate, or None after timeout_s."""
        deadline = time.monotonic() + timeout_s
        types = [types] if isinstance(types, str) else types
        while (left := deadline - time.monotonic()) > 0:
            msg = self.conn.recv_match(blocking=True, timeout=min(0.2, max(left, 0.01)))
            if msg is None:
                continue
            self.seen.append(msg)
            if msg.get_srcSystem() == self.sysid and msg.get_type() in types and predicate(msg):
                return msg
        return None

    def wait_heartbeat(self, timeout_s: float = 5.0):
        hb = self.recv("HEARTBEAT", timeout_s)
        if hb is None:
            raise LinkError(f"no heartbeat from system {self.sysid} on {self.uri} within {timeout_s:g} s")
        self.conn.target_system, self.conn.target_component = self.sysid, 1
        return hb

    def command(self, command: int, *params: float, timeout_s: float = 1.5, retries: int = 3) -> int:
        """Send COMMAND_LONG until its COMMAND_ACK arrives (confirmation counts retries); returns MAV_RESULT."""
        p = list(params) + [0.0] * (7 - len(params))
        for confirmation in range(retries):
            self.conn.mav.command_long_send(self.sysid, 1, command, confirmation, *p)
            ack = self.recv("COMMAND_ACK", timeout_s, lambda m: m.command == command)
            if ack is not None:
                return ack.result
        raise LinkError(f"no COMMAND_ACK for command {command} from system {self.sysid} after {retries} tries")

    def command_ok(self, command: int, *params: float, **kwargs) -> None:
        result = self.command(command, *params, **kwargs)
        if result != M.MAV_RESULT_ACCEPTED:
            raise CommandError(command, result)

    def set_mode(self, name: str) -> int:
        if name not in COPTER_MODES:
            raise ValueError(f"unknown mode {name!r}; known: {', '.join(sorted(COPTER_MODES))}")
        return self.command(MavCmd.DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES[name])

    def upload(self, items: list[MissionItem], mission_type: int = 0, timeout_s: float = 60.0,
               item_timeout_s: float = 1.5, progress=None) -> int:
        """Mission upload; re-sends COUNT or the last item when the vehicle goes quiet. Returns the ACK type."""
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
                    self.send_item(items[last_sent], mission_type)
                continue
            if msg.get_type() == "MISSION_ACK":
                return msg.type
            if not 0 <= msg.seq < len(items):
                continue
            last_sent = msg.seq
            self.send_item(items[msg.seq], mission_type)
            if progress is not None:
                progress(msg.seq + 1, len(items))
        raise MissionError(f"mission upload to system {self.sysid} timed out after {timeout_s:g} s")

    def send_item(self, it: MissionItem, mission_type: int) -> None:
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
            raise MissionError(f"mission download from system {self.sysid} timed out after {timeout_s:g} s")
        mav.mission_ack_send(self.sysid, 1, M.MAV_MISSION_ACCEPTED, mission_type)
        return items
