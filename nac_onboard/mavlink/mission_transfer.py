"""Mission transfer as a ground station does it (the client side of the mission protocol; the vehicle side is
sitl/mavlink/mission_protocol.py): upload with paced re-sends, download with re-requests, clear, set current.

A mix-in of MavlinkClient: it uses the client's `recv`, `_link_for`, `sysid` and `signing_hint`.
"""

from __future__ import annotations

import math

from missions.model import MavCmd, MissionItem
from nac_onboard.errors import OperationFailed
from nac_onboard.mavlink.dialect import M, enum_name


class MissionError(OperationFailed):
    def __init__(self, what: str, result: int | None = None):
        self.result = result
        if result is not None:
            what += f": {enum_name('MAV_MISSION_RESULT', result)}"
        super().__init__(what)


class MissionTransfer:
    last_item_sent: int | None = None  # in the last upload: a refusing MISSION_ACK answers this item
    def upload(self, items: list[MissionItem], mission_type: int = 0, item_timeout_s: float = 1.5,
               retries: int = 10, progress=None, sysid: int | None = None) -> int:
        """Mission upload as the protocol asks of a GCS: answer each request once; when the vehicle goes quiet
        for item_timeout_s, re-send COUNT (nothing requested yet) or the last item, at most `retries` times in
        a row. Returns the vehicle's MISSION_ACK type. The spec asks for at least 5 retries; 10 keeps a
        radio losing 30 % each way from failing one upload in fifty on a lost final ACK."""
        target = self.sysid if sysid is None else sysid
        conn = self._link_for(target)
        conn.mav.mission_count_send(target, 1, len(items), mission_type)
        last_sent, quiet_s = None, 0.0
        self.last_item_sent = None
        while True:
            # Mid-transfer the vehicle drives (it re-requests); before the first request and after the last item
            # only we can, so we re-send three times as often for the same total patience.
            we_drive = last_sent is None or last_sent == len(items) - 1
            timeout_s = item_timeout_s / 3 if we_drive else item_timeout_s
            msg = self.recv(["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"], timeout_s,
                            lambda m: m.mission_type == mission_type and m.target_system in (0, conn.mav.srcSystem),
                            sysid=target)
            if msg is None:
                quiet_s += timeout_s
                if quiet_s > retries * item_timeout_s + 1e-9:
                    waiting = "the first request" if last_sent is None else f"the answer to item {last_sent}"
                    raise MissionError(f"mission upload to vehicle {target} gave up: no answer ({waiting}) after "
                                       f"{quiet_s:.1f} s of retries.{self.signing_hint()}")
                if last_sent is None:
                    conn.mav.mission_count_send(target, 1, len(items), mission_type)
                else:
                    self.send_item(items[last_sent], mission_type, target)
                continue
            quiet_s = 0.0
            if msg.get_type() == "MISSION_ACK":
                return msg.type
            if not 0 <= msg.seq < len(items):
                continue
            last_sent = self.last_item_sent = msg.seq  # a refusal (the ACK) comes after the item it refuses
            self.send_item(items[msg.seq], mission_type, target)
            if progress is not None:
                progress(msg.seq + 1, len(items))

    def send_item(self, it: MissionItem, mission_type: int, sysid: int | None = None) -> None:
        target = self.sysid if sysid is None else sysid
        self._link_for(target).mav.mission_item_int_send(
            target, 1, it.seq, it.frame, it.command, 0, int(it.autocontinue), it.p1, it.p2, it.p3, it.p4,
            _e7(it.lat_deg), _e7(it.lon_deg), it.alt_m, mission_type)

    def download(self, mission_type: int = 0, item_timeout_s: float = 1.5, retries: int = 5, progress=None,
                 sysid: int | None = None) -> list[MissionItem]:
        target = self.sysid if sysid is None else sysid
        conn = self._link_for(target)
        count, quiet = None, 0
        while count is None:
            conn.mav.mission_request_list_send(target, 1, mission_type)
            msg = self.recv("MISSION_COUNT", item_timeout_s, lambda m: m.mission_type == mission_type, sysid=target)
            if msg is not None:
                count = msg.count
            elif (quiet := quiet + 1) > retries:
                raise MissionError(f"mission download from vehicle {target}: no MISSION_COUNT after {retries} "
                                   f"retries.{self.signing_hint()}")
        items: list[MissionItem] = []
        quiet = 0
        while len(items) < count:
            conn.mav.mission_request_int_send(target, 1, len(items), mission_type)
            msg = self.recv("MISSION_ITEM_INT", item_timeout_s, lambda m: m.seq == len(items), sysid=target)
            if msg is None:
                if (quiet := quiet + 1) > retries:
                    raise MissionError(f"mission download from vehicle {target}: item {len(items)} of {count} "
                                       f"never came after {retries} retries")
                continue
            quiet = 0
            items.append(MissionItem(msg.seq, msg.command, msg.frame, msg.param1, msg.param2, msg.param3,
                                     msg.param4, msg.x / 1e7, msg.y / 1e7, msg.z, bool(msg.autocontinue),
                                     mission_type=msg.mission_type))
            if progress is not None:
                progress(len(items), count)
        conn.mav.mission_ack_send(target, 1, M.MAV_MISSION_ACCEPTED, mission_type)
        return items

    def set_current(self, seq: int, sysid: int | None = None) -> None:
        """Make mission item `seq` the current one (MAV_CMD_DO_SET_MISSION_CURRENT)."""
        self.command_ok(MavCmd.DO_SET_MISSION_CURRENT, seq, sysid=sysid)

    def clear(self, mission_type: int = 0, timeout_s: float = 1.5, retries: int = 3,
              sysid: int | None = None) -> int:
        target = self.sysid if sysid is None else sysid
        for _ in range(retries):
            self._link_for(target).mav.mission_clear_all_send(target, 1, mission_type)
            ack = self.recv("MISSION_ACK", timeout_s, lambda m: m.mission_type == mission_type, sysid=target)
            if ack is not None:
                return ack.type
        raise MissionError(f"vehicle {target} did not acknowledge the mission clear after {retries} tries")


def _e7(degrees: float) -> int:
    """x or y of MISSION_ITEM_INT; NaN (unset, for a command without a position) goes out as 0, as QGC sends it."""
    return 0 if math.isnan(degrees) else int(round(degrees * 1e7))
