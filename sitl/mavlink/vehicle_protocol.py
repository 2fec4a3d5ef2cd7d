"""MAVLink protocol of one simulated vehicle: message handlers, parameters, missions, telemetry; its commands
are answered from the table in sitl.mavlink.commands.

The server's connections (UDP endpoints, TCP clients) deliver decoded messages here; everything the vehicle
says goes out through `send`, which encodes once and writes to one connection or all of them. The protocol
sees the world (sitl.vehicle), the stream table and the telemetry snapshot; it knows nothing of sockets.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from collections.abc import Callable

from missions.firmware import arducopter_refusal as validate_item
from missions.model import MavCmd, MissionItem, MissionType
from nac_onboard.mavlink.signing import SigningState
from sitl.mavlink.codec import FrameEncoder, mavlink
from sitl.mavlink.commands import CommandCall, Connection, answer
from sitl.mavlink.mission_protocol import Ack, Complete, MissionReceiver, Request
from sitl.mavlink.telemetry import BUILDERS, NOT_DATA_STREAMS, Streams, TelemetrySource
from sitl.vehicle import guided, pilot
from sitl.vehicle.flight import CommandOutcome, Event, Result, Severity
from sitl.vehicle.params import PARAM_DEFS, ParamError
from sitl.vehicle.world import World

log = logging.getLogger(__name__)
M = mavlink

CAPABILITIES = (
    M.MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT | M.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    | M.MAV_PROTOCOL_CAPABILITY_MISSION_INT | M.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
    | M.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | M.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    | M.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE | M.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY
)
PARAM_TYPES = {"INT8": M.MAV_PARAM_TYPE_INT8, "INT16": M.MAV_PARAM_TYPE_INT16, "INT32": M.MAV_PARAM_TYPE_INT32,
               "REAL32": M.MAV_PARAM_TYPE_REAL32}
FTP_HEADER = struct.Struct("<HBBBBBBI")  # seq, session, opcode, size, req_opcode, burst_complete, padding, offset
FTP_TERMINATE_SESSION, FTP_RESET_SESSIONS, FTP_ACK, FTP_NAK = 1, 2, 128, 129
FTP_ERR_FILE_NOT_FOUND = 10
RESTART_S = 3.0  # simulated seconds a rebooting autopilot is silent
FLIGHT_SW_VERSION = (4 << 24) | (5 << 16) | (7 << 8) | 255  # 4.5.7 official: what an ArduCopter of today says


def _item_from_msg(msg, is_int: bool) -> MissionItem:
    lat = msg.x / 1e7 if is_int else float(msg.x)
    lon = msg.y / 1e7 if is_int else float(msg.y)
    return MissionItem(
        seq=msg.seq, command=msg.command, frame=msg.frame, p1=msg.param1, p2=msg.param2, p3=msg.param3,
        p4=msg.param4, lat_deg=lat, lon_deg=lon, alt_m=float(msg.z), autocontinue=bool(msg.autocontinue),
        current=bool(msg.current), mission_type=getattr(msg, "mission_type", 0),
    )


class VehicleProtocol:
    def __init__(self, index: int, world: World, streams: Streams, telemetry: TelemetrySource,
                 signing: SigningState | None = None, clock: Callable[[], float] = time.monotonic):
        self.i = index
        self.sysid = index + 1
        self.world = world
        self.autopilots = world.autopilots
        self.streams = streams
        self.telemetry = telemetry
        self.encoder = FrameEncoder(self.sysid, 1, signing=signing)
        self.connections: list[Connection] = []
        self.receiver = MissionReceiver(validate_item)
        self.clock = clock  # wall clock: mission transfer timeouts are the client's, in real seconds
        self.on_params_changed()
        self._pending_transfer = None
        self._refused_frames: set[tuple[str, int]] = set()
        self.silent_until_t_s = -math.inf  # restarting: nothing in or out until then (simulated seconds)

    def on_params_changed(self) -> None:
        self.receiver.item_timeout_s = self.world.params.get(self.i, "SIM_MIS_RETRY_MS") / 1000.0

    # ---- output -------------------------------------------------------------------------------------
    def send(self, frame: bytes, channel: Connection | None = None) -> None:
        if self.world.t_s < self.silent_until_t_s:
            return
        if channel is not None:
            channel.write(frame)
            return
        for connection in self.connections:
            connection.write(frame)

    def send_msg(self, msg, channel: Connection | None = None) -> None:
        self.send(self.encoder.message(msg), channel)

    def statustext(self, severity: Severity, text: str) -> None:
        self.send_msg(M.MAVLink_statustext_message(severity, text.encode()[:50]))

    # ---- input --------------------------------------------------------------------------------------
    def handle(self, msg, channel: Connection) -> None:
        kind = msg.get_type()
        handler = _HANDLERS.get(kind)
        if handler is None or self.world.t_s < self.silent_until_t_s:
            return
        target = getattr(msg, "target_system", None)
        if target is not None and target not in (0, self.sysid):
            return
        target_comp = getattr(msg, "target_component", None)
        if target_comp is not None and target_comp not in (0, 1):
            return
        handler(self, msg, channel)

    def _partner(self, msg, channel: Connection) -> tuple:
        return (msg.get_srcSystem(), msg.get_srcComponent(), id(channel))

    # ---- commands: the table in sitl.mavlink.commands ----------------------------------------------
    def _on_command(self, msg, channel: Connection) -> None:
        reply = answer(self, CommandCall.from_msg(msg))
        outcome = reply.outcome
        if outcome.text:
            self.statustext(Severity.INFO if outcome.result == Result.ACCEPTED else Severity.WARNING, outcome.text)
        ack = M.MAVLink_command_ack_message(msg.command, int(outcome.result), 0, 0, msg.get_srcSystem(),
                                            msg.get_srcComponent())
        self.send_msg(ack, channel)
        if reply.then is not None:  # a requested message follows its ACK
            reply.then(channel)

    def restart(self) -> None:
        """The autopilot restarts after answering: silent for RESTART_S, then its boot clock starts again at 0
        and its streams are back to their defaults (what the agent's reconnect logic sees on a Pixhawk)."""
        back_t_s = self.world.t_s + RESTART_S
        self.silent_until_t_s = back_t_s
        self.world.boot_t_s[self.i] = back_t_s
        self.streams.reset(self.i, back_t_s)
        sysid = int(self.world.params.get(self.i, "SYSID_THISMAV"))  # a new SYSID_THISMAV takes effect now
        if sysid != self.sysid:
            log.info("vehicle %d comes back as sysid %d", self.sysid, sysid)
            self.sysid = sysid
            self.encoder = FrameEncoder(sysid, 1, signing=self.encoder.signing)
        log.info("vehicle %d restarting (back at t = %.1f s)", self.sysid, back_t_s)

    def set_interval(self, msgid: int, interval_us: float) -> CommandOutcome:
        if not self.streams.set_interval(self.i, msgid, interval_us, self.world.t_s):
            return CommandOutcome(Result.UNSUPPORTED, f"Message {msgid} cannot be streamed")
        return CommandOutcome(Result.ACCEPTED)

    def _on_set_mode(self, msg, channel: Connection) -> None:
        result = Result.DENIED
        if msg.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            outcome = self.autopilots.set_mode(self.i, msg.custom_mode)
            result = outcome.result  # a mode this copter does not have is refused, not ACCEPTED and ignored
            if outcome.text:
                self.statustext(Severity.WARNING, outcome.text)
        # ArduPilot answers the legacy message with a COMMAND_ACK for DO_SET_MODE as well.
        self.send_msg(M.MAVLink_command_ack_message(MavCmd.DO_SET_MODE, int(result), 0, 0,
                                                    msg.get_srcSystem(), msg.get_srcComponent()), channel)

    def _on_request_data_stream(self, msg, channel: Connection) -> None:
        rate_hz = msg.req_message_rate
        stop = msg.start_stop == 0 or rate_hz == 0
        for msgid in BUILDERS:
            if msgid not in NOT_DATA_STREAMS:
                self.set_interval(msgid, -1 if stop else 1e6 / rate_hz)

    def _on_position_target(self, msg, channel: Connection) -> None:
        """GUIDED setpoints, frames and type mask as ArduCopter reads them (sitl.vehicle.guided). Like
        ArduCopter, nothing answers them: a frame it does not take is dropped, and said once per frame."""
        vel, acc = (msg.vx, msg.vy, msg.vz), (msg.afx, msg.afy, msg.afz)
        if msg.get_type() == "SET_POSITION_TARGET_GLOBAL_INT":
            pos = None
            if guided.position_used(msg.type_mask):
                pos = self.world.global_to_enu(self.i, msg.lat_int / 1e7, msg.lon_int / 1e7, msg.alt,
                                               relative=msg.coordinate_frame in guided.GLOBAL_RELATIVE_FRAMES)
            target = guided.global_setpoint(msg.coordinate_frame, msg.type_mask, pos, vel, acc, msg.yaw,
                                            msg.yaw_rate)
        else:
            state = self.world.state
            target = guided.local_setpoint(msg.coordinate_frame, msg.type_mask, (msg.x, msg.y, msg.z), vel, acc,
                                           msg.yaw, msg.yaw_rate, state.pos_m[self.i].copy(),
                                           float(state.yaw_rad[self.i]))
        if target is None:
            key = (msg.get_type(), msg.coordinate_frame)
            if key not in self._refused_frames:
                self._refused_frames.add(key)
                self.statustext(Severity.WARNING, f"{msg.get_type()[20:]}: frame {msg.coordinate_frame} ignored")
            return
        self.autopilots.setpoint(self.i, target)

    def _on_file_transfer(self, msg, channel: Connection) -> None:
        """MAVFTP: no files here. Every request is answered at once with a NAK (FileNotFound; a session reset or
        end with an ACK), so a ground station falls back to the parameter protocol without waiting out its FTP
        timeout (MAVProxy waited about 1.5 s on every fetch)."""
        payload = bytes(msg.payload)
        if len(payload) < FTP_HEADER.size:
            return
        seq, session, opcode, _size, _req, _burst, _pad, _offset = FTP_HEADER.unpack_from(payload)
        if opcode in (FTP_ACK, FTP_NAK):
            return
        done = opcode in (FTP_TERMINATE_SESSION, FTP_RESET_SESSIONS)
        reply = FTP_HEADER.pack((seq + 1) & 0xFFFF, session, FTP_ACK if done else FTP_NAK, 0 if done else 1, opcode,
                                0, 0, 0) + (b"" if done else bytes([FTP_ERR_FILE_NOT_FOUND]))
        self.send_msg(M.MAVLink_file_transfer_protocol_message(
            0, msg.get_srcSystem(), msg.get_srcComponent(), list(reply.ljust(251, b"\0"))), channel)

    def _on_rc_override(self, msg, channel: Connection) -> None:
        # a MAVLink 1 sender has no channels 9-18: they stay as they are
        self.autopilots.rc_override(self.i, [getattr(msg, f"chan{k}_raw", pilot.IGNORE) for k in range(1, 17)])

    def _on_timesync(self, msg, channel: Connection) -> None:
        if msg.tc1 == 0:
            now_ns = int(self.telemetry.unix_time_s() * 1e9)
            self.send_msg(M.MAVLink_timesync_message(now_ns, msg.ts1), channel)

    # ---- parameters ---------------------------------------------------------------------------------
    def param_value(self, index: int):
        definition = PARAM_DEFS[index]
        value = self.world.params.reported(self.i, definition.name)
        # ArduPilot sends integers as their value in the float field ("C-cast"), typed as it stores them
        return M.MAVLink_param_value_message(definition.name.encode(), value, PARAM_TYPES[definition.kind],
                                             len(PARAM_DEFS), index)

    def _on_param_request_list(self, msg, channel: Connection) -> None:
        for index in range(len(PARAM_DEFS)):
            self.send_msg(self.param_value(index), channel)

    def _on_param_request_read(self, msg, channel: Connection) -> None:
        index = msg.param_index
        if index < 0:
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id
            index = next((k for k, d in enumerate(PARAM_DEFS) if d.name == name), -1)
        if 0 <= index < len(PARAM_DEFS):
            self.send_msg(self.param_value(index), channel)

    def _on_param_set(self, msg, channel: Connection) -> None:
        name = msg.param_id.rstrip("\x00")
        index = next((k for k, d in enumerate(PARAM_DEFS) if d.name == name), -1)
        if index < 0:
            self.statustext(Severity.WARNING, f"Param {name[:30]} unknown")
            return
        try:
            note = self.world.store_param(self.i, name, float(msg.param_value))
        except ParamError as err:
            note = str(err)
        if note:
            self.statustext(Severity.WARNING, note[:50])
        self.send_msg(self.param_value(index))  # always echo, changed or not, to every channel

    # ---- missions -----------------------------------------------------------------------------------
    def _mission_actions(self, actions, msg, channel: Connection) -> None:
        for action in actions:
            if isinstance(action, Request):
                self.send_msg(M.MAVLink_mission_request_int_message(
                    msg.get_srcSystem(), msg.get_srcComponent(), action.seq, action.mission_type), channel)
            elif isinstance(action, Ack):
                self.send_msg(M.MAVLink_mission_ack_message(
                    msg.get_srcSystem(), msg.get_srcComponent(), int(action.result), action.mission_type), channel)
            elif isinstance(action, Complete):
                self.autopilots.replace_mission(self.i, action.mission_type, action.items)
        self.autopilots.transfer_busy[self.i] = self.receiver.busy

    def _on_mission_count(self, msg, channel: Connection) -> None:
        partner = self._partner(msg, channel)
        actions = self.receiver.on_count(partner, msg.mission_type, msg.count, self.clock())
        if self.receiver.upload is not None and self.receiver.upload.partner == partner:
            self._pending_transfer = (msg, channel)  # re-requests go to the uploader, not to a denied second GCS
        self._mission_actions(actions, msg, channel)

    def _on_mission_item(self, msg, channel: Connection) -> None:
        item = _item_from_msg(msg, msg.get_type() == "MISSION_ITEM_INT")
        actions = self.receiver.on_item(self._partner(msg, channel), item, self.clock())
        self._mission_actions(actions, msg, channel)

    def poll_transfers(self, now_s: float) -> None:
        if self.receiver.upload is None:
            return
        actions = self.receiver.poll(now_s)
        if actions:
            msg, channel = self._pending_transfer
            self._mission_actions(actions, msg, channel)

    def download_items(self, mission_type: int) -> list[MissionItem]:
        items = list(self.autopilots.mission(self.i, mission_type))
        if mission_type == MissionType.MISSION:
            home = self.world.home_of(self.i)
            # ArduPilot's item 0 is always the current home, whatever was uploaded there.
            home_item = MissionItem(0, MavCmd.NAV_WAYPOINT, frame=0, lat_deg=home.lat_deg, lon_deg=home.lon_deg,
                                    alt_m=home.alt_m)
            items = [home_item] + items[1:]
        return items

    def _known_type(self, msg, channel: Connection) -> bool:
        """Answer a request for a mission type that does not exist with MAV_MISSION_UNSUPPORTED."""
        if msg.mission_type in (MissionType.MISSION, MissionType.FENCE, MissionType.RALLY):
            return True
        self.send_msg(M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                    M.MAV_MISSION_UNSUPPORTED, msg.mission_type), channel)
        return False

    def _on_mission_request_list(self, msg, channel: Connection) -> None:
        if not self._known_type(msg, channel):
            return
        count = len(self.download_items(msg.mission_type))
        self.send_msg(M.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(), count,
                                                      msg.mission_type), channel)

    def _on_mission_request(self, msg, channel: Connection) -> None:
        if not self._known_type(msg, channel):
            return
        items = self.download_items(msg.mission_type)
        if not 0 <= msg.seq < len(items):
            self.send_msg(M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(),
                                                        M.MAV_MISSION_INVALID_SEQUENCE, msg.mission_type), channel)
            return
        it = items[msg.seq]
        on_it = msg.mission_type == MissionType.MISSION and it.seq == self.autopilots.current_seq[self.i]
        current = 1 if on_it else 0
        self.send_msg(M.MAVLink_mission_item_int_message(
            msg.get_srcSystem(), msg.get_srcComponent(), it.seq, it.frame, it.command, current,
            int(it.autocontinue), it.p1, it.p2, it.p3, it.p4, int(round(it.lat_deg * 1e7)),
            int(round(it.lon_deg * 1e7)), it.alt_m, msg.mission_type), channel)

    def _on_mission_ack(self, msg, channel: Connection) -> None:
        self._mission_actions(self.receiver.on_ack(self._partner(msg, channel)), msg, channel)

    def _on_mission_clear_all(self, msg, channel: Connection) -> None:
        everything = msg.mission_type == M.MAV_MISSION_TYPE_ALL
        if not everything and not self._known_type(msg, channel):
            return
        if self.receiver.busy:
            result = M.MAV_MISSION_DENIED
        else:
            for mission_type in (MissionType if everything else [msg.mission_type]):
                self.autopilots.replace_mission(self.i, mission_type, [])
            result = M.MAV_MISSION_ACCEPTED
        self.send_msg(M.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), result,
                                                    msg.mission_type), channel)

    def _on_mission_set_current(self, msg, channel: Connection) -> None:
        outcome = self.autopilots.set_current(self.i, msg.seq)
        if outcome.result != Result.ACCEPTED:
            self.statustext(Severity.WARNING, outcome.text)

    # ---- telemetry ----------------------------------------------------------------------------------
    def on_event(self, kind: Event, value) -> None:
        if kind is Event.ITEM_REACHED:
            self.send_msg(M.MAVLink_mission_item_reached_message(int(value)))
        elif kind is Event.MISSION_CURRENT:
            self.send_one(M.MAVLINK_MSG_ID_MISSION_CURRENT)
        elif kind in (Event.MODE, Event.ARMED):
            self.send_one(M.MAVLINK_MSG_ID_HEARTBEAT)
        elif kind is Event.TEXT:
            severity, text = value
            self.statustext(severity, text)
        elif kind is Event.HOME:
            self.send_one(M.MAVLINK_MSG_ID_HOME_POSITION)

    def build(self, msgid: int) -> bytes:
        return BUILDERS[msgid](self.encoder, self.i, self.world, self.telemetry.current())

    def send_one(self, msgid: int, channel: Connection | None = None) -> None:
        if msgid == M.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            uid = self.sysid
            msg = M.MAVLink_autopilot_version_message(
                CAPABILITIES, FLIGHT_SW_VERSION, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0x4E41, 0x0001, uid)
            self.send_msg(msg, channel)
            return
        self.send(self.build(msgid), channel)


_HANDLERS = {
    "COMMAND_LONG": VehicleProtocol._on_command,
    "COMMAND_INT": VehicleProtocol._on_command,
    "SET_MODE": VehicleProtocol._on_set_mode,
    "REQUEST_DATA_STREAM": VehicleProtocol._on_request_data_stream,
    "SET_POSITION_TARGET_GLOBAL_INT": VehicleProtocol._on_position_target,
    "SET_POSITION_TARGET_LOCAL_NED": VehicleProtocol._on_position_target,
    "TIMESYNC": VehicleProtocol._on_timesync,
    "RC_CHANNELS_OVERRIDE": VehicleProtocol._on_rc_override,
    "FILE_TRANSFER_PROTOCOL": VehicleProtocol._on_file_transfer,
    "PARAM_REQUEST_LIST": VehicleProtocol._on_param_request_list,
    "PARAM_REQUEST_READ": VehicleProtocol._on_param_request_read,
    "PARAM_SET": VehicleProtocol._on_param_set,
    "MISSION_COUNT": VehicleProtocol._on_mission_count,
    "MISSION_ITEM_INT": VehicleProtocol._on_mission_item,
    "MISSION_ITEM": VehicleProtocol._on_mission_item,
    "MISSION_REQUEST_LIST": VehicleProtocol._on_mission_request_list,
    "MISSION_REQUEST_INT": VehicleProtocol._on_mission_request,
    "MISSION_REQUEST": VehicleProtocol._on_mission_request,
    "MISSION_ACK": VehicleProtocol._on_mission_ack,
    "MISSION_CLEAR_ALL": VehicleProtocol._on_mission_clear_all,
    "MISSION_SET_CURRENT": VehicleProtocol._on_mission_set_current,
}
