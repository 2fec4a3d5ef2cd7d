"""The commands (COMMAND_LONG, COMMAND_INT) a simulated vehicle answers: `COMMANDS`, one handler per MAV_CMD.

A handler takes the vehicle it answers for (`CommandTarget`: its index, world, flight logic, streams and
outputs) and the command as it arrived (`CommandCall`: the four parameters, the place, and the frame and
altitude reference the place is in), and returns a `Reply`: the outcome its COMMAND_ACK carries, with the text
said beside it, and what is sent after the ACK for the commands that ask for a message. Nothing is kept between
commands. A command without a handler is answered UNSUPPORTED, as every command gets an ACK.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import Protocol

import numpy as np

from missions.model import MavCmd
from sitl.mavlink.codec import FrameEncoder, ProtocolVersionMessage, mavlink
from sitl.mavlink.telemetry import BUILDERS, Streams
from sitl.vehicle.flight import FORCE_DISARM_MAGIC, OK, Autopilots, CommandOutcome, CopterMode, Result
from sitl.vehicle.world import World

M = mavlink
AMSL_FRAMES = frozenset({M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT})


class Connection(Protocol):
    """Where a vehicle's frames go: one client of one of its links (the server's UDP peer or TCP connection)."""

    def write(self, frame: bytes) -> None: ...


class AltRef(Enum):
    """What a command's altitude is measured from."""

    HOME = "home"  # COMMAND_INT in any frame but the two below: above home
    AMSL = "amsl"  # COMMAND_INT in MAV_FRAME_GLOBAL or MAV_FRAME_GLOBAL_INT: above mean sea level
    UNSTATED = "unstated"  # COMMAND_LONG has no frame: each command takes ArduPilot's convention for it


@dataclass(frozen=True)
class CommandCall:
    """One command as received: COMMAND_INT's place scaled to degrees, COMMAND_LONG's params 5-7 as sent."""

    command: int
    p: tuple[float, float, float, float]  # param1..param4
    x: float  # latitude, degrees
    y: float  # longitude, degrees
    z: float  # altitude, m, from alt_ref
    frame: int | None  # COMMAND_INT's MAV_FRAME; None for COMMAND_LONG
    alt_ref: AltRef

    @classmethod
    def from_msg(cls, msg) -> CommandCall:
        p = (msg.param1, msg.param2, msg.param3, msg.param4)
        if msg.get_type() == "COMMAND_INT":
            alt_ref = AltRef.AMSL if msg.frame in AMSL_FRAMES else AltRef.HOME
            return cls(msg.command, p, msg.x / 1e7, msg.y / 1e7, float(msg.z), msg.frame, alt_ref)
        return cls(msg.command, p, msg.param5, msg.param6, msg.param7, None, AltRef.UNSTATED)

    def has_location(self) -> bool:
        return math.isfinite(self.x) and math.isfinite(self.y) and -90 <= self.x <= 90 and -180 <= self.y <= 180


@dataclass(frozen=True)
class Reply:
    outcome: CommandOutcome
    then: Callable[[Connection], None] | None = None  # sent after the COMMAND_ACK, to the one who asked


class CommandTarget(Protocol):
    """What a handler may use of the vehicle it answers for (sitl.mavlink.vehicle_protocol.VehicleProtocol)."""

    i: int
    world: World
    autopilots: Autopilots
    streams: Streams
    encoder: FrameEncoder

    def send(self, frame: bytes, channel: Connection | None = None) -> None: ...

    def send_msg(self, msg, channel: Connection | None = None) -> None: ...

    def send_one(self, msgid: int, channel: Connection | None = None) -> None: ...

    def set_interval(self, msgid: int, interval_us: float) -> CommandOutcome: ...

    def restart(self) -> None: ...


Handler = Callable[[CommandTarget, CommandCall], Reply]


def answer(v: CommandTarget, call: CommandCall) -> Reply:
    """The reply to one command: its handler's, or UNSUPPORTED."""
    handler = COMMANDS.get(call.command)
    return Reply(CommandOutcome(Result.UNSUPPORTED)) if handler is None else handler(v, call)


def _place_m(v: CommandTarget, call: CommandCall, alt: float, relative: bool) -> np.ndarray:
    return v.world.global_to_enu(v.i, call.x, call.y, alt, relative=relative)


# ---- flying ---------------------------------------------------------------------------------------------------
def _arm_disarm(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.arm(v.i, call.p[0] >= 0.5, force=int(call.p[1]) == FORCE_DISARM_MAGIC))


def _takeoff(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.takeoff(v.i, call.z))


def _land(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.set_mode(v.i, CopterMode.LAND))


def _return_to_launch(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.set_mode(v.i, CopterMode.RTL))


def _loiter_unlimited(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.set_mode(v.i, CopterMode.LOITER))


def _mission_start(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.mission_start(v.i, int(call.p[0])))


def _set_mode(v: CommandTarget, call: CommandCall) -> Reply:
    if not int(call.p[0]) & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
        return Reply(CommandOutcome(Result.DENIED, "Mode change refused: only custom modes are supported"))
    return Reply(v.autopilots.set_mode(v.i, int(call.p[1])))


def _set_mission_current(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.set_current(v.i, int(call.p[0])))


def _change_speed(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.change_speed(v.i, call.p[1]))


def _reposition(v: CommandTarget, call: CommandCall) -> Reply:
    """DO_REPOSITION: COMMAND_LONG's altitude is above home, COMMAND_INT's by its frame."""
    return Reply(v.autopilots.goto(v.i, _place_m(v, call, call.z, relative=call.alt_ref is not AltRef.AMSL)))


def _condition_yaw(v: CommandTarget, call: CommandCall) -> Reply:
    p = call.p
    return Reply(v.autopilots.condition_yaw(v.i, p[0], p[1], p[2], p[3] >= 0.5))


def _roi_location(v: CommandTarget, call: CommandCall) -> Reply:
    """DO_SET_ROI_LOCATION (and DO_SET_ROI with MAV_ROI_LOCATION): altitude as DO_REPOSITION's, NaN is 0."""
    if not call.has_location():
        return Reply(CommandOutcome(Result.DENIED, "ROI refused: no location"))
    alt = call.z if math.isfinite(call.z) else 0.0
    return Reply(v.autopilots.set_roi(v.i, _place_m(v, call, alt, relative=call.alt_ref is not AltRef.AMSL)))


def _roi_none(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.set_roi(v.i, None))


def _roi(v: CommandTarget, call: CommandCall) -> Reply:
    """The deprecated DO_SET_ROI: a location, or (every other ROI mode) no region of interest."""
    return (_roi_location if int(call.p[0]) == M.MAV_ROI_LOCATION else _roi_none)(v, call)


def _pause_continue(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.pause(v.i, int(call.p[0]) == 0))


def _set_servo(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.set_servo(v.i, int(call.p[0]), int(call.p[1])))


def _fence_enable(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.autopilots.enable_fence(v.i, call.p[0]))


def _set_home(v: CommandTarget, call: CommandCall) -> Reply:
    """DO_SET_HOME: here (param1 = 1) or a place. ArduPilot takes COMMAND_LONG's altitude as above mean sea level,
    COMMAND_INT's by its frame."""
    if call.p[0] >= 0.5:
        return Reply(v.autopilots.set_home(v.i, None))
    if not call.has_location() or call.x == call.y == 0:
        return Reply(CommandOutcome(Result.DENIED, "Set home refused: no location"))
    return Reply(v.autopilots.set_home(v.i, _place_m(v, call, call.z, relative=call.alt_ref is AltRef.HOME)))


def _reboot(v: CommandTarget, call: CommandCall) -> Reply:
    """PREFLIGHT_REBOOT_SHUTDOWN: the autopilot (param1 = 1) restarts once it has answered."""
    if int(call.p[0]) != 1:
        return Reply(CommandOutcome(Result.UNSUPPORTED, "Only an autopilot reboot (param1 = 1) is simulated"))
    outcome = v.autopilots.reboot(v.i)
    if outcome.result != Result.ACCEPTED:
        return Reply(outcome)
    return Reply(outcome, lambda channel: v.restart())


# ---- messages asked for ----------------------------------------------------------------------------------------
def can_send(msgid: int) -> bool:
    return msgid in BUILDERS or msgid in (M.MAVLINK_MSG_ID_AUTOPILOT_VERSION,)


def _request_message(v: CommandTarget, call: CommandCall) -> Reply:
    msgid = int(call.p[0])
    if not can_send(msgid):
        return Reply(CommandOutcome(Result.UNSUPPORTED))
    return Reply(OK, lambda channel: v.send_one(msgid, channel))


def _request_autopilot_capabilities(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(OK, lambda channel: v.send_one(M.MAVLINK_MSG_ID_AUTOPILOT_VERSION, channel))


def _get_home_position(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(OK, lambda channel: v.send_one(M.MAVLINK_MSG_ID_HOME_POSITION, channel))


def _set_message_interval(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(v.set_interval(int(call.p[0]), call.p[1]))


def _get_message_interval(v: CommandTarget, call: CommandCall) -> Reply:
    msgid = int(call.p[0])
    interval = v.streams.interval_of(v.i, msgid) or 0.0
    us = int(interval * 1e6) if 0 < interval < math.inf else -1
    return Reply(OK, lambda channel: v.send_msg(M.MAVLink_message_interval_message(msgid, us), channel))


def _request_protocol_version(v: CommandTarget, call: CommandCall) -> Reply:
    return Reply(OK, lambda channel: v.send(v.encoder.fields(
        ProtocolVersionMessage, 200, 100, 200, bytes(8), bytes(8)), channel))


COMMANDS: dict[int, Handler] = {
    MavCmd.COMPONENT_ARM_DISARM: _arm_disarm,
    MavCmd.NAV_TAKEOFF: _takeoff,
    MavCmd.NAV_LAND: _land,
    MavCmd.NAV_RETURN_TO_LAUNCH: _return_to_launch,
    M.MAV_CMD_NAV_LOITER_UNLIM: _loiter_unlimited,
    MavCmd.MISSION_START: _mission_start,
    MavCmd.DO_SET_MODE: _set_mode,
    MavCmd.DO_SET_MISSION_CURRENT: _set_mission_current,
    MavCmd.DO_CHANGE_SPEED: _change_speed,
    M.MAV_CMD_DO_REPOSITION: _reposition,
    M.MAV_CMD_CONDITION_YAW: _condition_yaw,
    M.MAV_CMD_DO_SET_ROI_LOCATION: _roi_location,
    M.MAV_CMD_DO_SET_ROI: _roi,
    M.MAV_CMD_DO_SET_ROI_NONE: _roi_none,
    M.MAV_CMD_DO_PAUSE_CONTINUE: _pause_continue,
    M.MAV_CMD_DO_SET_SERVO: _set_servo,
    M.MAV_CMD_DO_FENCE_ENABLE: _fence_enable,
    M.MAV_CMD_DO_SET_HOME: _set_home,
    M.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN: _reboot,
    MavCmd.REQUEST_MESSAGE: _request_message,
    MavCmd.REQUEST_AUTOPILOT_CAPABILITIES: _request_autopilot_capabilities,
    M.MAV_CMD_GET_HOME_POSITION: _get_home_position,
    MavCmd.SET_MESSAGE_INTERVAL: _set_message_interval,
    M.MAV_CMD_GET_MESSAGE_INTERVAL: _get_message_interval,
    M.MAV_CMD_REQUEST_PROTOCOL_VERSION: _request_protocol_version,
}
