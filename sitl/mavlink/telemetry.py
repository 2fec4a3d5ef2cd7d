"""What the simulated vehicles stream: the stream table (rates per vehicle and message), a per-step snapshot of
the world in MAVLink units computed once for every vehicle, and one builder per message."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl.mavlink.codec import FrameEncoder, mavlink
from sitl.vehicle.flight import Check, CopterMode, MissionState
from sitl.vehicle.physics import Motion, VehicleState, attitude_rad
from sitl.vehicle.world import World

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
    M.MAVLINK_MSG_ID_RC_CHANNELS: 1.0,
    M.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: 1.0,
    M.MAVLINK_MSG_ID_EKF_STATUS_REPORT: 1.0,
}
STREAM_IDS = tuple(DEFAULT_INTERVALS_S)
#: not in any of ArduPilot's REQUEST_DATA_STREAM groups: sent on change or on request, at their own rate
NOT_DATA_STREAMS = frozenset({M.MAVLINK_MSG_ID_HEARTBEAT, M.MAVLINK_MSG_ID_HOME_POSITION,
                              M.MAVLINK_MSG_ID_SYSTEM_TIME, M.MAVLINK_MSG_ID_MISSION_CURRENT})
STREAM_COLUMN = {msgid: column for column, msgid in enumerate(STREAM_IDS)}
MIN_STREAM_INTERVAL_S = 0.02  # 50 Hz per message, like ArduPilot's stream-rate ceiling
EKF_WITHOUT_GPS = M.EKF_ATTITUDE | M.EKF_VELOCITY_VERT | M.EKF_POS_VERT_ABS
EKF_WITH_GPS = EKF_WITHOUT_GPS | M.EKF_VELOCITY_HORIZ | M.EKF_POS_HORIZ_REL | M.EKF_POS_HORIZ_ABS \
    | M.EKF_PRED_POS_HORIZ_REL | M.EKF_PRED_POS_HORIZ_ABS
SENSORS = (M.MAV_SYS_STATUS_SENSOR_3D_GYRO | M.MAV_SYS_STATUS_SENSOR_3D_ACCEL | M.MAV_SYS_STATUS_SENSOR_3D_MAG
           | M.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | M.MAV_SYS_STATUS_SENSOR_GPS
           | M.MAV_SYS_STATUS_SENSOR_BATTERY)


class Streams:
    """Interval and next due time of every streamed message of every vehicle, as (N, messages) arrays."""

    def __init__(self, vehicles: int):
        self.interval_s = np.tile(np.array([DEFAULT_INTERVALS_S[m] for m in STREAM_IDS]), (vehicles, 1))
        self.next_due_s = np.zeros((vehicles, len(STREAM_IDS)))

    def due(self, t_s: float) -> list[tuple[int, int]]:
        """(vehicle, msgid) of every message due at t_s, each rescheduled one interval on."""
        due = self.next_due_s <= t_s
        if not due.any():
            return []
        self.next_due_s[due] = np.maximum(self.next_due_s[due] + self.interval_s[due], t_s)
        rows, columns = np.nonzero(due)
        return [(vehicle, STREAM_IDS[column]) for vehicle, column in zip(rows.tolist(), columns.tolist(), strict=True)]

    def reset(self, vehicle: int, t_s: float) -> None:
        """Every stream of a vehicle back to its default (a restarted autopilot forgets what was asked)."""
        self.interval_s[vehicle] = [DEFAULT_INTERVALS_S[m] for m in STREAM_IDS]
        self.next_due_s[vehicle] = t_s

    def interval_of(self, vehicle: int, msgid: int) -> float | None:
        """Seconds between messages (inf when disabled), None for a message that is not streamed."""
        column = STREAM_COLUMN.get(msgid)
        return None if column is None else float(self.interval_s[vehicle, column])

    def set_interval(self, vehicle: int, msgid: int, interval_us: float, t_s: float) -> bool:
        """SET_MESSAGE_INTERVAL semantics: < 0 disables, 0 restores the default; False for an unknown message."""
        column = STREAM_COLUMN.get(msgid)
        if column is None:
            return False
        if interval_us < 0:
            interval_s = math.inf
        elif interval_us == 0:
            interval_s = DEFAULT_INTERVALS_S[msgid]
        else:
            interval_s = max(interval_us / 1e6, MIN_STREAM_INTERVAL_S)
        self.interval_s[vehicle, column] = interval_s
        self.next_due_s[vehicle, column] = t_s
        return True


@dataclass
class Telemetry:
    """Per-step snapshot of what the vehicles report, in MAVLink's integer units, computed once for all."""

    state: VehicleState
    time_boot_ms: int  # of the simulation (the snapshot's key)
    boot_ms: list  # of each vehicle's autopilot: a rebooted one starts again from 0
    time_usec: int
    lat_e7: list
    lon_e7: list
    alt_mm: list
    rel_alt_mm: list
    vn_cms: list
    ve_cms: list
    vd_cms: list
    hdg_cdeg: list
    roll: list
    pitch: list
    yaw: list
    landed_state: list


class TelemetrySource:
    """The world's current snapshot (made at most once per step) and the autopilot's clocks."""

    def __init__(self, world: World, epoch_unix_s: float):
        self.world = world
        self.epoch_unix_s = epoch_unix_s  # unix time at simulated t = 0
        self._snapshot: Telemetry | None = None

    def unix_time_s(self) -> float:
        return self.epoch_unix_s + self.world.t_s

    def current(self) -> Telemetry:
        if self._snapshot is None or self._snapshot.time_boot_ms != int(self.world.t_s * 1000):
            self._snapshot = self._take()
        return self._snapshot

    def _take(self) -> Telemetry:
        w = self.world
        s = w.state
        fix = w.gps_fix()
        roll, pitch, yaw = attitude_rad(s)
        hdg = np.mod(np.degrees(yaw), 360.0)
        landed = np.where(s.on_ground, M.MAV_LANDED_STATE_ON_GROUND,
                          np.where(w.autopilots.motion == Motion.LAND, M.MAV_LANDED_STATE_LANDING,
                                   M.MAV_LANDED_STATE_IN_AIR))
        climbing = (w.autopilots.check == Check.ALTITUDE) & ~s.on_ground
        landed = np.where(climbing, M.MAV_LANDED_STATE_TAKEOFF, landed)

        def ints(values) -> list:
            return np.round(values).astype(np.int64).tolist()

        return Telemetry(
            state=s, time_boot_ms=int(w.t_s * 1000), boot_ms=ints(np.maximum(w.t_s - w.boot_t_s, 0.0) * 1000),
            time_usec=int(self.unix_time_s() * 1e6),
            lat_e7=ints(fix.lat_deg * 1e7), lon_e7=ints(fix.lon_deg * 1e7), alt_mm=ints(fix.alt_m * 1000),
            rel_alt_mm=ints((fix.pos_m[:, 2] - w.autopilots.home_m[:, 2]) * 1000), vn_cms=ints(s.vel_mps[:, 1] * 100),
            ve_cms=ints(s.vel_mps[:, 0] * 100), vd_cms=ints(-s.vel_mps[:, 2] * 100), hdg_cdeg=ints(hdg * 100),
            roll=roll.tolist(), pitch=pitch.tolist(), yaw=yaw.tolist(), landed_state=landed.tolist(),
        )


# ---- one builder per streamed message: (encoder, vehicle, world, snapshot) -> frame ----------------------------
def heartbeat_fields(world: World, i: int) -> tuple:
    f = world.autopilots
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


def _heartbeat(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    return enc.fields(M.MAVLink_heartbeat_message, *heartbeat_fields(w, i))


def _global_position(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    return enc.fields(M.MAVLink_global_position_int_message, t.boot_ms[i], t.lat_e7[i], t.lon_e7[i],
                      t.alt_mm[i], t.rel_alt_mm[i], t.vn_cms[i], t.ve_cms[i], t.vd_cms[i], t.hdg_cdeg[i])


def _local_position(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    p, v = t.state.pos_m[i], t.state.vel_mps[i]
    return enc.fields(M.MAVLink_local_position_ned_message, t.boot_ms[i], float(p[1]), float(p[0]),
                      float(-p[2]), float(v[1]), float(v[0]), float(-v[2]))


def _attitude(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    return enc.fields(M.MAVLink_attitude_message, t.boot_ms[i], float(t.roll[i]), float(t.pitch[i]),
                      float(t.yaw[i]), 0.0, 0.0, 0.0)


def _vfr_hud(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    v = t.state.vel_mps[i]
    speed = float(math.hypot(v[0], v[1]))
    throttle = 50 if w.autopilots.armed[i] and not t.state.on_ground[i] else 0
    return enc.fields(M.MAVLink_vfr_hud_message, speed, speed, int(t.hdg_cdeg[i] // 100), throttle,
                      t.alt_mm[i] / 1000.0, float(v[2]))


def _sys_status(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    """As ArduCopter fills it: the geofence is present, enabled by FENCE_ENABLE, healthy unless breached;
    PREARM_CHECK is healthy while the pre-arm checks pass (MAVSDK's is_armable)."""
    present = SENSORS | M.MAV_SYS_STATUS_GEOFENCE | M.MAV_SYS_STATUS_PREARM_CHECK
    enabled = present if w.params.get(i, "FENCE_ENABLE") else present & ~M.MAV_SYS_STATUS_GEOFENCE
    health = present if w.autopilots.gps_ok[i] else present & ~M.MAV_SYS_STATUS_SENSOR_GPS
    if w.autopilots.fence_breach[i] is not None:
        health &= ~M.MAV_SYS_STATUS_GEOFENCE
    if w.autopilots.prearm_failure(i):
        health &= ~M.MAV_SYS_STATUS_PREARM_CHECK
    return enc.fields(
        M.MAVLink_sys_status_message, present, enabled, health, 200, int(t.state.voltage_v[i] * 1000),
        int(t.state.current_a[i] * 100), int(round(t.state.soc[i] * 100)), 0, 0, 0, 0, 0, 0, 0, 0, 0)


def _battery(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    s = t.state
    cells = int(w.params.get(i, "BATT_CELLS"))
    per_cell_mv = int(s.voltage_v[i] * 1000 / cells)
    voltages = [per_cell_mv] * min(cells, 10) + [65535] * (10 - min(cells, 10))
    msg = M.MAVLink_battery_status_message(
        0, M.MAV_BATTERY_FUNCTION_ALL, M.MAV_BATTERY_TYPE_LIPO, 32767, voltages, int(s.current_a[i] * 100),
        int(s.consumed_mah[i]), int(s.consumed_wh[i] * 36), int(round(s.soc[i] * 100)), 0,  # 1 Wh = 36 hJ
        M.MAV_BATTERY_CHARGE_STATE_LOW if w.autopilots.failsafe[i] else M.MAV_BATTERY_CHARGE_STATE_OK,
        [0, 0, 0, 0], 0, 0)
    return enc.message(msg)


def _gps_raw(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    ok = w.autopilots.gps_ok[i]
    v = t.state.vel_mps[i]
    fix_type = M.GPS_FIX_TYPE_3D_FIX if ok else M.GPS_FIX_TYPE_NO_FIX
    return enc.fields(
        M.MAVLink_gps_raw_int_message, t.time_usec, fix_type, t.lat_e7[i], t.lon_e7[i], t.alt_mm[i],
        90 if ok else 9999, 150 if ok else 9999, int(math.hypot(v[0], v[1]) * 100), t.hdg_cdeg[i],
        12 if ok else 0, t.alt_mm[i], 500, 800, 200, 0, 0)


def _extended_sys_state(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    return enc.fields(M.MAVLink_extended_sys_state_message, M.MAV_VTOL_STATE_UNDEFINED, int(t.landed_state[i]))


def _mission_current(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    f = w.autopilots
    total = max(len(f.mission(i)) - 1, 0)
    state = int(f.mission_state[i]) if total else int(MissionState.NO_MISSION)
    in_auto = 1 if f.mode[i] == CopterMode.AUTO else 2  # MISSION_CURRENT.mission_mode: 1 in mission mode
    return enc.fields(M.MAVLink_mission_current_message, int(f.current_seq[i]), total, state, in_auto)


def _home_position(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    home, east, north, up = w.home_of(i), *w.autopilots.home_m[i].tolist()
    msg = M.MAVLink_home_position_message(
        int(round(home.lat_deg * 1e7)), int(round(home.lon_deg * 1e7)), int(round(home.alt_m * 1000)),
        north, east, -up, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t.time_usec)
    return enc.message(msg)


def _rc_channels(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    return enc.fields(M.MAVLink_rc_channels_message, t.boot_ms[i], 16, *w.autopilots.rc_us[i].tolist(), 0, 0, 255)


def _servo_output_raw(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    """Motors 1-4 as an ESC sees them (stopped, spinning armed, about hover in flight), then DO_SET_SERVO's."""
    f = w.autopilots
    motor = 1000 if not f.armed[i] else (1100 if t.state.on_ground[i] else 1500)
    servos = [f.servo_pwm[i].get(k, 0) for k in range(5, 17)]
    return enc.fields(M.MAVLink_servo_output_raw_message, t.time_usec & 0xFFFFFFFF, 0, motor, motor, motor, motor,
                      *servos)


def _ekf_status(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    """A healthy EKF with GPS; without it, attitude and height only (what makes ArduCopter's EKF failsafe)."""
    flags = EKF_WITH_GPS if w.autopilots.gps_ok[i] else EKF_WITHOUT_GPS
    horizontal = 0.02 if w.autopilots.gps_ok[i] else 1.0
    return enc.fields(M.MAVLink_ekf_status_report_message, flags, 0.02, horizontal, 0.02, 0.02, 0.0, 0.0)


def _system_time(enc: FrameEncoder, i: int, w: World, t: Telemetry) -> bytes:
    return enc.fields(M.MAVLink_system_time_message, t.time_usec, t.boot_ms[i])


BUILDERS = {
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
    M.MAVLINK_MSG_ID_RC_CHANNELS: _rc_channels,
    M.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW: _servo_output_raw,
    M.MAVLINK_MSG_ID_EKF_STATUS_REPORT: _ekf_status,
}
