"""MAVLink protocol of one simulated vehicle: message handlers, commands, parameters, missions, telemetry.

Channels (UDP endpoints, TCP clients) deliver decoded messages here; everything the vehicle says goes out
through `send`, which encodes once and writes to one channel or all of them.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING

import numpy as np

from missions.model import MavCmd, MissionItem, MissionType
from sitl.mavlink.codec import FrameEncoder, mavlink
from sitl.mavlink.mission_protocol import Ack, Complete, MissionReceiver, Request
from sitl.vehicle.flight import CopterMode, Fleet, MissionState, Outcome, Result, validate_item
from sitl.vehicle.params import PARAM_DEFS, ParamError

if TYPE_CHECKING:
    from sitl.server import Channel, Telemetry

log = logging.getLogger(__name__)
M = mavlink

#: Default stream intervals (simulated seconds), the messages of DESIGN.md section 3.
DEFAULT_INTERVALS_S: dict[int, float] = {
    M.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    M.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    M.MAVLINK_MSG_ID_SYSTEM_TIME: 2.0,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: 0.5,
    M.MAVLINK_MSG_ID_ATTITUDE: 0.25,
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.25,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 0.5,
    M.MAVLINK_MSG_ID_VFR_HUD: 0.5,
    M.MAVLINK_MSG_ID_BATTERY_STATUS: 1.0,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 1.0,
    M.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    M.MAVLINK_MSG_ID_HOME_POSITION: 5.0,
}
STREAM_IDS = tuple(DEFAULT_INTERVALS_S)
STREAM_COLUMN = {msgid: column for column, msgid in enumerate(STREAM_IDS)}
MIN_STREAM_INTERVAL_S = 0.02  # 50 Hz per message, like ArduPilot's stream-rate ceiling
CAPABILITIES = (
    M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | M.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE | M.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)
FLIGHT_SW_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | 255  # 4.5.7 official: what an ArduCopter of today says
SENSORS = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL | M.MAV_SYS_STATUS_SENSOR_3D_MAG
           | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | M.MAV_SYS_STATUS_SENSOR_GPS
           | M.MAV_SYS_STATUS_SENSOR_BATTERY)


def _item_from_msg(msg, is_int: bool) -> MissionItem:
    lat = msg.x / 1e7 if is_int else float(msg.x)
    lon = msg.y / 1e7 if is_int else float(msg.y)
    return MissionItem(
        seq=msg.seq, command=msg.command, frame=msg.frame, p1=msg.param1, p2=msg.param2, p3=msg.param3,
        p4=msg.param4, lat_deg=lat, lon_deg=lon, alt_m=float(msg.z), autocontinue=bool(msg.autocontinue),
        current=bool(msg.current), mission_type=getattr(msg, "mission_type", 0),
    )


class VehicleLink:
    def __init__(self, index: int, fleet: Fleet, sim):
        self.i = index
        self.sysid = index + 1
        self.fleet = fleet
        self.sim = sim  # the server: clock, channels, parameters, telemetry snapshot
        self.encoder = FrameEncoder(self.sysid, 1, signing_key=sim.config.signing_key)
        self.channels: list[Channel] = []
        self.receiver = MissionReceiver(validate_item)
        self._after_ack: list = []
        self._command_alt_amsl = False
        self._pending_transfer = None

    # ---- output -------------------------------------------------------------------------------------
    def send(self, frame: bytes, channel: Channel | None = None) -> None:
        if channel is not None:
            channel.write(frame)
            return
        for ch in self.channels:
            ch.write(frame)

    def send_msg(self, msg, channel: Channel | None = None) -> None:
        self.send(self.encoder.message(msg), channel)

    def statustext(self, severity: int, text: str) -> None:
        self.send_msg(M.MAVLink_statustext_message(severity, text.encode()[:50]))

    # ---- input --------------------------------------------------------------------------------------
    def handle(self, msg, channel: Channel) -> None:
        kind = msg.get_type()
        handler = _HANDLERS.get(kind)
        if handler is None:
            return
        target = getattr(msg, "target_system", None)
        if target is not None and target not in (0, self.sysid):
            return
        target_comp = getattr(msg, "target_component", None)
        if target_comp is not None and target_comp not in (0, 1):
            return
        handler(self, msg, channel)

    def _partner(self, msg, channel: Channel) -> tuple:
        return (msg.get_srcSystem(), msg.get_srcComponent(), id(channel))

    # ---- commands -----------------------------------------------------------------------------------
    def _on_command(self, msg, channel: Channel) -> None:
        is_int = msg.get_type() == "COMMAND_INT"
        params = [msg.param1, msg.param2, msg.param3, msg.param4]
        if is_int:
            x, y, z = msg.x / 1e7, msg.y / 1e7, float(msg.z)
            self._command_alt_amsl = msg.frame in (M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT)
        else:
            x, y, z = msg.param5, msg.param6, msg.param7
            self._command_alt_amsl = False  # COMMAND_LONG carries no frame: altitude relative to home
        outcome = self.command(msg.command, params, x, y, z, channel)
        if outcome.text:
            self.statustext(6 if outcome.result == Result.ACCEPTED else 4, outcome.text)
        ack = M.MAVLink_command_ack_message(msg.command, int(outcome.result), 0, 0, msg.get_srcSystem(),
                                            msg.get_srcComponent())
        self.send_msg(ack, channel)
        deferred, self._after_ack = self._after_ack, []
        for send_after in deferred:  # a requested message follows its ACK
            send_after()

    def command(self, command: int, p: list[float], x: float, y: float, z: float, channel: Channel) -> Outcome:
        f, i = self.fleet, self.i
        if command == MavCmd.COMPONENT_ARM_DISARM:
            return f.arm(i, p[0] >= 0.5, force=int(p[1]) == 21196)
        if command == MavCmd.NAV_TAKEOFF:
            return f.takeoff(i, z)
        if command == MavCmd.NAV_LAND:
            return f.set_mode(i, CopterMode.LAND)
        if command == MavCmd.NAV_RETURN_TO_LAUNCH:
            return f.set_mode(i, CopterMode.RTL)
        if command == MavCmd.MISSION_START:
            return f.mission_start(i, int(p[0]))
        if command == MavCmd.DO_SET_MODE:
            if not int(p[0]) & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                return Outcome(Result.DENIED, "Mode change refused: only custom modes are supported")
            return f.set_mode(i, int(p[1]))
        if command == MavCmd.DO_SET_MISSION_CURRENT:
            return f.set_current(i, int(p[0]))
        if command == MavCmd.DO_CHANGE_SPEED:
            return f.change_speed(i, p[1])
        if command == MavCmd.REQUEST_MESSAGE:
            msgid = int(p[0])
            if not self._can_send(msgid):
                return Outcome(Result.UNSUPPORTED)
            self._after_ack.append(lambda: self.send_one(msgid, channel))
            return Outcome(Result.ACCEPTED)
        if command == MavCmd.REQUEST_AUTOPILOT_CAPABILITIES:
            self._after_ack.append(lambda: self.send_one(M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, channel))
            return Outcome(Result.ACCEPTED)
        if command == MavCmd.SET_MESSAGE_INTERVAL:
            return self.set_interval(int(p[0]), p[1])
        if command == M.MAV_CMD_GET_MESSAGE_INTERVAL:
            msgid = int(p[0])
            column = STREAM_COLUMN.get(msgid)
            interval = self.sim.stream_interval_s[i, column] if column is not None else 0.0
            us = int(interval * 1e6) if 0 < interval < math.inf else -1
            self._after_ack.append(lambda: self.send_msg(M.MAVLink_message_interval_message(msgid, us), channel))
            return Outcome(Result.ACCEPTED)
        if command == M.MAV_CMD_DO_REPOSITION:
            return f.goto(i, self.sim.global_to_enu(i, x, y, z, relative=not self._command_alt_amsl))
        return Outcome(Result.UNSUPPORTED)

    def set_interval(self, msgid: int, interval_us: float) -> Outcome:
        column = STREAM_COLUMN.get(msgid)
        if column is None:
            return Outcome(Result.UNSUPPORTED, f"Message {msgid} cannot be streamed")
        if interval_us < 0:
            interval_s = math.inf  # disabled
        elif interval_us == 0:
            interval_s = DEFAULT_INTERVALS_S[msgid]
        else:
            interval_s = max(interval_us / 1e6, MIN_STREAM_INTERVAL_S)
        self.sim.stream_interval_s[self.i, column] = interval_s
        self.sim.stream_next_due_s[self.i, column] = self.sim.t_s
        return Outcome(Result.ACCEPTED)

    def _can_send(self, msgid: int) -> bool:
        return msgid in _BUILDERS or msgid in (M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,)

    def _on_set_mode(self, msg, channel: Channel) -> None:
        if msg.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            outcome = self.fleet.set_mode(self.i, msg.custom_mode)
            if outcome.text:
                self.statustext(4, outcome.text)
        # ArduPilot answers the legacy message with a COMMAND_ACK for DO_SET_MODE as well.
        result = Result.ACCEPTED if msg.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED else Result.DENIED
        self.send_msg(M.MAVLink_command_ack_message(MavCmd.DO_SET_MODE, int(result), 0, 0,
                                                    msg.get_srcSystem(), msg.get_srcComponent()), channel)

    def _on_request_data_stream(self, msg, channel: Channel) -> None:
        rate_hz = msg.req_message_rate
        stop = msg.start_stop == 0 or rate_hz == 0
        for msgid in STREAM_IDS:
            if msgid != M.MAVLINK_MSG_ID_HEARTBEAT:
                self.set_interval(msgid, -1 if stop else 1e6 / rate_hz)

    def _on_position_target(self, msg, channel: Channel) -> None:
        if msg.get_type() == "SET_POSITION_TARGET_GLOBAL_INT":
            goal = self.sim.global_to_enu(self.i, msg.lat_int / 1e7, msg.lon_int / 1e7, msg.alt,
                                          relative=msg.coordinate_frame != M.MAV_FRAME_GLOBAL_INT)
        else:
            goal = np.array([msg.y, msg.x, -msg.z])  # NED -> ENU
        self.fleet.goto(self.i, goal)

    def _on_timesync(self, msg, channel: Channel) -> None:
        if msg.tc1 == 0:
            now_ns = int(self.sim.unix_time_s() * 1e9)
            self.send_msg(M.MAVLink_timesync_message(now_ns, msg.ts1), channel)

    # ---- parameters ---------------------------------------------------------------------------------
    def param_value(self, index: int):
        definition = PARAM_DEFS[index]
        value = self.sim.params.get(self.i, definition.name)
        return M.MAVLink_param_value_message(definition.name.encode(), value, M.MAV_PARAM_TYPE_REAL32,
                                             len(PARAM_DEFS), index)

    def _on_param_request_list(self, msg, channel: Channel) -> None:
        for index in range(len(PARAM_DEFS)):
            self.send_msg(self.param_value(index), channel)

    def _on_param_request_read(self, msg, channel: Channel) -> None:
        index = msg.param_index
        if index < 0:
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id
            index = next((k for k, d in enumerate(PARAM_DEFS) if d.name == name), -1)
        if 0 <= index < len(PARAM_DEFS):
            self.send_msg(self.param_value(index), channel)

    def _on_param_set(self, msg, channel: Channel) -> None:
        name = msg.param_id.rstrip("\x00")
        index = next((k for k, d in enumerate(PARAM_DEFS) if d.name == name), -1)
        if index < 0:
            self.statustext(4, f"Param {name[:30]} unknown")
            return
        try:
            self.sim.set_param(self.i, name, float(msg.param_value))
        except ParamError as err:
            self.statustext(4, str(err)[:50])
        self.send_msg(self.param_value(index))  # always echo, changed or not, to every channel

    # ---- missions -----------------------------------------------------------------------------------
    def _mission_actions(self, actions, msg, channel: Channel) -> None:
        for action in actions:
            if isinstance(action, Request):
                self.send_msg(M.MAVLink_mission_request_int_message(
                    msg.get_srcSystem(), msg.get_srcComponent(), action.seq, action.mission_type), channel)
            elif isinstance(action, Ack):
                self.send_msg(M.MAVLink_mission_ack_message(
                    msg.get_srcSystem(), msg.get_srcComponent(), int(action.result), action.mission_type), channel)
            elif isinstance(action, Complete):
                self.fleet.replace_mission(self.i, action.mission_type, action.items)
        self.fleet.transfer_busy[self.i] = self.receiver.busy

    def _on_mission_count(self, msg, channel: Channel) -> None:
        partner = self._partner(msg, channel)
        actions = self.receiver.on_count(partner, msg.mission_type, msg.count, self.sim.wall_s())
        if self.receiver.upload is not None and self.receiver.upload.partner == partner:
            self._pending_transfer = (msg, channel)  # re-requests go to the uploader, not to a denied second GCS
        self._mission_actions(actions, msg, channel)

    def _on_mission_item(self, msg, channel: Channel) -> None:
        item = _item_from_msg(msg, msg.get_type() == "MISSION_ITEM_INT")
        actions = self.receiver.on_item(self._partner(msg, channel), item, self.sim.wall_s())
        self._mission_actions(actions, msg, channel)

    def poll_transfers(self, now_s: float) -> None:
        if self.receiver.upload is None:
            return
        actions = self.receiver.poll(now_s)
        if actions:
            msg, channel = self._pending_transfer
            self._mission_actions(actions, msg, channel)

    def download_items(self, mission_type: int) -> list[MissionItem]:
        items = list(self.fleet.mission(self.i, mission_type))
        if mission_type == MissionType.MISSION:
            home = self.sim.homes[self.i]
            # ArduPilot's item 0 is always the current home, whatever was uploaded there.
            home_item = MissionItem(0, MavCmd.NAV_WAYPOINT, frame=0, lat_deg=home.lat_deg, lon_deg=home.lon_deg,
                                    alt_m=home.alt_m)
            items = [home_item] + items[1:]
        return items

    def _known_type(self, msg, channel: Channel) -> bool:
        """Answer a request for a mission type that does not exist with MAV_MISSION_UNSUPPORTED."""
        if msg.mission_type in (MissionType.MISSION, MissionType.FENCE, MissionType.RALLY):
            return True
        self.send_msg(M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                    M.MAV_MISSION_UNSUPPORTED, msg.mission_type), channel)
        return False

    def _on_mission_request_list(self, msg, channel: Channel) -> None:
        if not self._known_type(msg, channel):
            return
        count = len(self.download_items(msg.mission_type))
        self.send_msg(M.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(), count,
                                                      msg.mission_type), channel)

    def _on_mission_request(self, msg, channel: Channel) -> None:
        if not self._known_type(msg, channel):
            return
        items = self.download_items(msg.mission_type)
        if not 0 <= msg.seq < len(items):
            self.send_msg(M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                        M.MAV_MISSION_INVALID_SEQUENCE, msg.mission_type), channel)
            return
        it = items[msg.seq]
        current = 1 if (msg.mission_type == MissionType.MISSION and it.seq == self.fleet.current_seq[self.i]) else 0
        self.send_msg(M.MAVLink_mission_item_int_message(
            msg.get_srcSystem(), msg.get_srcComponent(), it.seq, it.frame, it.command, current,
            int(it.autocontinue), it.p1, it.p2, it.p3, it.p4, int(round(it.lat_deg * 1e7)),
            int(round(it.lon_deg * 1e7)), it.alt_m, msg.mission_type), channel)

    def _on_mission_ack(self, msg, channel: Channel) -> None:
        self._mission_actions(self.receiver.on_ack(self._partner(msg, channel)), msg, channel)

    def _on_mission_clear_all(self, msg, channel: Channel) -> None:
        everything = msg.mission_type == M.MAV_MISSION_TYPE_ALL
        if not everything and not self._known_type(msg, channel):
            return
        if self.receiver.busy:
            result = M.MAV_MISSION_DENIED
        else:
            for mission_type in (MissionType if everything else [msg.mission_type]):
                self.fleet.replace_mission(self.i, mission_type, [])
            result = M.MAV_MISSION_ACCEPTED
        self.send_msg(M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), result,
                                                    msg.mission_type), channel)

    def _on_mission_set_current(self, msg, channel: Channel) -> None:
        outcome = self.fleet.set_current(self.i, msg.seq)
        if outcome.result != Result.ACCEPTED:
            self.statustext(4, outcome.text)

    # ---- telemetry ----------------------------------------------------------------------------------
    def on_event(self, kind: str, value) -> None:
        if kind == "item_reached":
            self.send_msg(M.MAVLink_mission_item_reached_message(int(value)))
        elif kind == "mission_current":
            self.send_one(M.MAVLINK_MSG_ID_MISSION_CURRENT)
        elif kind in ("mode", "armed"):
            self.send_one(M.MAVLINK_MSG_ID_HEARTBEAT)
        elif kind == "text":
            severity, text = value
            self.statustext(severity, text)

    def build(self, msgid: int, telemetry: Telemetry) -> bytes:
        return _BUILDERS[msgid](self, telemetry)

    def send_one(self, msgid: int, channel: Channel | None = None) -> None:
        if msgid == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            uid = self.sysid
            msg = M.MAVLink_autopilot_version_message(
                CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x4E41, 0x0001, uid)
            self.send_msg(msg, channel)
            return
        self.send(self.build(msgid, self.sim.telemetry()), channel)

    def heartbeat_fields(self):
        f, i = self.fleet, self.i
        mode = int(f.mode[i])
        base = M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | M.MAV_MODE_FLAG_STABILIZE_ENABLED
        if f.armed[i]:
            base |= M.MAV_MODE_FLAG_SAFETY_ARMED
        if mode in (CopterMode.GUIDED, CopterMode.AUTO, CopterMode.RTL, CopterMode.LAND):
            base |= M.MAV_MODE_FLAG_GUIDED_ENABLED
        if mode == CopterMode.AUTO:
            base |= M.MAV_MODE_FLAG_AUTO_ENABLED
        if f.failsafe[i]:
            status = M.MAV_STATE_CRITICAL
        else:
            status = M.MAV_STATE_ACTIVE if f.armed[i] else M.MAV_STATE_STANDBY
        return (M.MAV_TYPE_QUADROTOR, M.MAV_AUTOPILOT_ARDUPILOTMEGA, base, mode, status, 3)


def _heartbeat(link: VehicleLink, t: Telemetry) -> bytes:
    return link.encoder.fields(M.MAVLink_heartbeat_message, *link.heartbeat_fields())


def _global_position(link: VehicleLink, t: Telemetry) -> bytes:
    i = link.i
    return link.encoder.fields(M.MAVLink_global_position_int_message, t.time_boot_ms, t.lat_e7[i], t.lon_e7[i],
                               t.alt_mm[i], t.rel_alt_mm[i], t.vn_cms[i], t.ve_cms[i], t.vd_cms[i], t.hdg_cdeg[i])


def _local_position(link: VehicleLink, t: Telemetry) -> bytes:
    i = link.i
    p, v = t.state.pos_m[i], t.state.vel_mps[i]
    return link.encoder.fields(M.MAVLink_local_position_ned_message, t.time_boot_ms, float(p[1]), float(p[0]),
                               float(-p[2]), float(v[1]), float(v[0]), float(-v[2]))


def _attitude(link: VehicleLink, t: Telemetry) -> bytes:
    i = link.i
    return link.encoder.fields(M.MAVLink_attitude_message, t.time_boot_ms, float(t.roll[i]), float(t.pitch[i]),
                               float(t.yaw[i]), 0.0, 0.0, 0.0)


def _vfr_hud(link: VehicleLink, t: Telemetry) -> bytes:
    i = link.i
    v = t.state.vel_mps[i]
    speed = float(math.hypot(v[0], v[1]))
    throttle = 50 if link.fleet.armed[i] and not t.state.on_ground[i] else 0
    return link.encoder.fields(M.MAVLink_vfr_hud_message, speed, speed, int(t.hdg_cdeg[i] // 100), throttle,
                               t.alt_mm[i] / 1000.0, float(v[2]))


def _sys_status(link: VehicleLink, t: Telemetry) -> bytes:
    i = link.i
    health = SENSORS if link.fleet.gps_ok[i] else SENSORS & ~M.MAV_SYS_STATUS_SENSOR_GPS
    return link.encoder.fields(
        M.MAVLink_sys_status_message, SENSORS, SENSORS, health, 200, int(t.state.voltage_v[i] * 1000),
        int(t.state.current_a[i] * 100), int(round(t.state.soc[i] * 100)), 0, 0, 0, 0, 0, 0, 0, 0, 0)


def _battery(link: VehicleLink, t: Telemetry) -> bytes:
    i = link.i
    s = t.state
    cells = int(link.sim.params.get(i, "BATT_CELLS"))
    per_cell_mv = int(s.voltage_v[i] * 1000 / cells)
    voltages = [per_cell_mv] * min(cells, 10) + [65535] * (10 - min(cells, 10))
    msg = M.MAVLink_battery_status_message(
        0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, voltages, int(s.current_a[i] * 100),
        int(s.consumed_mah[i]), -1, int(round(s.soc[i] * 100)), 0,
        M.MAV_BATTERY_CHARGE_STATE_LOW if link.fleet.failsafe[i] else M.MAV_BATTERY_CHARGE_STATE_OK,
        [0, 0, 0, 0], 0, 0)
    return link.encoder.message(msg)


def _gps_raw(link: VehicleLink, t: Telemetry) -> bytes:
    i = link.i
    ok = link.fleet.gps_ok[i]
    v = t.state.vel_mps[i]
    return link.encoder.fields(
        M.MAVLink_gps_raw_int_message, t.time_usec, 3 if ok else 1, t.lat_e7[i], t.lon_e7[i], t.alt_mm[i],
        90 if ok else 9999, 150 if ok else 9999, int(math.hypot(v[0], v[1]) * 100), t.hdg_cdeg[i],
        12 if ok else 0, t.alt_mm[i], 500, 800, 200, 0, 0)


def _extended_sys_state(link: VehicleLink, t: Telemetry) -> bytes:
    return link.encoder.fields(M.MAVLink_extended_sys_state_message, M.MAV_VTOL_STATE_UNDEFINED,
                               int(t.landed_state[link.i]))


def _mission_current(link: VehicleLink, t: Telemetry) -> bytes:
    f, i = link.fleet, link.i
    total = max(len(f.mission(i)) - 1, 0)
    state = int(f.mission_state[i]) if total else int(MissionState.NO_MISSION)
    in_auto = 1 if f.mode[i] == CopterMode.AUTO else 2
    return link.encoder.fields(M.MAVLink_mission_current_message, int(f.current_seq[i]), total, state, in_auto)


def _home_position(link: VehicleLink, t: Telemetry) -> bytes:
    home = link.sim.homes[link.i]
    msg = M.MAVLink_home_position_message(
        int(round(home.lat_deg * 1e7)), int(round(home.lon_deg * 1e7)), int(round(home.alt_m * 1000)),
        0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t.time_usec)
    return link.encoder.message(msg)


def _system_time(link: VehicleLink, t: Telemetry) -> bytes:
    return link.encoder.fields(M.MAVLink_system_time_message, t.time_usec, t.time_boot_ms)


_BUILDERS = {
    M.MAVLINK_MSG_ID_HEARTBEAT: _heartbeat,
    M.MAVLINK_MSG_ID_SYS_STATUS: _sys_status,
    M.MAVLINK_MSG_ID_SYSTEM_TIME: _system_time,
    M.MAVLINK_MSG_ID_GPS_RAW_INT: _gps_raw,
    M.MAVLINK_MSG_ID_ATTITUDE: _attitude,
    M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: _global_position,
    M.MAVLINK_MSG_ID_LOCAL_POSITION_NED: _local_position,
    M.MAVLINK_MSG_ID_VFR_HUD: _vfr_hud,
    M.MAVLINK_MSG_ID_BATTERY_STATUS: _battery,
    M.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: _extended_sys_state,
    M.MAVLINK_MSG_ID_MISSION_CURRENT: _mission_current,
    M.MAVLINK_MSG_ID_HOME_POSITION: _home_position,
}

_HANDLERS = {
    "COMMAND_LONG": VehicleLink._on_command,
    "COMMAND_INT": VehicleLink._on_command,
    "SET_MODE": VehicleLink._on_set_mode,
    "REQUEST_DATA_STREAM": VehicleLink._on_request_data_stream,
    "SET_POSITION_TARGET_GLOBAL_INT": VehicleLink._on_position_target,
    "SET_POSITION_TARGET_LOCAL_NED": VehicleLink._on_position_target,
    "TIMESYNC": VehicleLink._on_timesync,
    "PARAM_REQUEST_LIST": VehicleLink._on_param_request_list,
    "PARAM_REQUEST_READ": VehicleLink._on_param_request_read,
    "PARAM_SET": VehicleLink._on_param_set,
    "MISSION_COUNT": VehicleLink._on_mission_count,
    "MISSION_ITEM_INT": VehicleLink._on_mission_item,
    "MISSION_ITEM": VehicleLink._on_mission_item,
    "MISSION_REQUEST_LIST": VehicleLink._on_mission_request_list,
    "MISSION_REQUEST_INT": VehicleLink._on_mission_request,
    "MISSION_REQUEST": VehicleLink._on_mission_request,
    "MISSION_ACK": VehicleLink._on_mission_ack,
    "MISSION_CLEAR_ALL": VehicleLink._on_mission_clear_all,
    "MISSION_SET_CURRENT": VehicleLink._on_mission_set_current,
}
