"""What commands and mission DO items ask of a simulated autopilot beyond its mode (pure): GUIDED goals and
setpoints, speed, heading and region of interest, pause and continue, servos, home, the fence switch.

Each takes a vehicle index and returns a `CommandOutcome` (a MAV_RESULT and what to tell the operator); the
MAVLink layer's command table (sitl.mavlink.commands) decodes the messages, mission_run calls the same for the
DO items of a running mission.
"""

from __future__ import annotations

import math

import numpy as np

from sitl.vehicle.flight_state import (
    HOME_FROM_ORIGIN_MAX_M,
    OK,
    Check,
    CommandOutcome,
    CopterMode,
    Event,
    FlightState,
    MissionState,
    Phase,
    Result,
)
from sitl.vehicle.guided import VELOCITY_TIMEOUT_S, Setpoint
from sitl.vehicle.physics import Motion


class Actions:
    """The guided and DO_* actions of N autopilots over their shared flight state."""

    def __init__(self, s: FlightState):
        self.s = s

    def change_speed(self, i: int, speed_mps: float) -> CommandOutcome:
        s = self.s
        if not math.isfinite(speed_mps) or speed_mps <= 0 or speed_mps > 50:
            return CommandOutcome(Result.DENIED, f"Speed {speed_mps} m/s outside 0..50")
        s.speed_xy_mps[i] = speed_mps
        return OK

    def goto(self, i: int, goal_m) -> CommandOutcome:
        s = self.s
        if s.mode[i] != CopterMode.GUIDED or not s.flying(i):
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Goto refused: needs GUIDED mode and flying")
        goal = np.asarray(goal_m, dtype=float).copy()
        goal[2] = max(goal[2], 0.5)
        s.set_goal(i, goal, Motion.GOTO, Check.NONE)
        return OK

    def setpoint(self, i: int, target: Setpoint) -> bool:
        """A GUIDED setpoint (sitl.vehicle.guided); ignored, as ArduCopter does, outside GUIDED or on the
        ground. Returns whether it was taken."""
        s = self.s
        if s.mode[i] != CopterMode.GUIDED or not s.flying(i):
            return False
        if target.pos_m is not None:
            self.goto(i, target.pos_m)
        elif target.is_velocity_control:
            s.velocity_mps[i] = target.vel_mps if target.vel_mps is not None else s.state.vel_mps[i]
            s.accel_mps2[i] = target.acc_mps2 if target.acc_mps2 is not None else 0.0
            s.set_goal(i, s.pos(i), Motion.VELOCITY, Check.NONE)
            s.timer(i, VELOCITY_TIMEOUT_S, Phase.VELOCITY)
        else:
            s.hold(i)  # every group ignored: ArduCopter stops
        s.yaw_target_rad[i] = math.nan if target.yaw_rad is None else target.yaw_rad
        s.yaw_rate_rps[i] = math.nan if target.yaw_rate_rps is None else target.yaw_rate_rps
        return True

    def condition_yaw(self, i: int, angle_deg: float, speed_dps: float, direction: float,
                      relative: bool) -> CommandOutcome:
        """CONDITION_YAW: turn to a heading (relative: by an angle, -1 counter-clockwise, 1 clockwise) at a
        rate (0: the vehicle's default)."""
        s = self.s
        if not (math.isfinite(angle_deg) and 0.0 <= angle_deg <= 360.0 and math.isfinite(speed_dps)):
            return CommandOutcome(Result.DENIED, f"Yaw refused: angle {angle_deg} outside 0..360")
        heading = float(s.state.yaw_rad[i]) if s.state is not None else 0.0
        turn = math.radians(angle_deg)
        s.yaw_target_rad[i] = heading + (-turn if direction < 0 else turn) if relative else turn
        s.yaw_rate_rps[i] = math.radians(abs(speed_dps)) if speed_dps else math.nan
        s.roi_m[i] = math.nan
        return OK

    def set_roi(self, i: int, roi_m) -> CommandOutcome:
        """DO_SET_ROI_LOCATION / DO_SET_ROI: point the nose at a place (None: stop doing so)."""
        s = self.s
        if roi_m is None:
            s.roi_m[i] = math.nan
            s.yaw_target_rad[i] = math.nan
        else:
            s.roi_m[i] = roi_m
        return OK

    def pause(self, i: int, pause: bool) -> CommandOutcome:
        """DO_PAUSE_CONTINUE in AUTO or GUIDED: stop where the vehicle is, then go on with what it was doing."""
        s = self.s
        if s.mode[i] not in (CopterMode.AUTO, CopterMode.GUIDED) or not s.flying(i):
            return CommandOutcome(Result.DENIED, "Pause/continue: needs AUTO or GUIDED and flying")
        if pause:
            if s.paused[i] is None:
                left_s = s.until_t_s[i] - s.t_s if s.check[i] == Check.TIMER else math.inf
                s.paused[i] = (s.goal_m[i].copy(), int(s.motion[i]), int(s.check[i]), float(s.radius_m[i]),
                               s.phase[i], left_s, int(s.mission_state[i]))
                s.set_goal(i, s.pos(i), Motion.GOTO, Check.NONE)
                if s.mode[i] == CopterMode.AUTO:
                    s.mission_state[i] = MissionState.PAUSED
                s.text(i, "Paused")
            return OK
        saved, s.paused[i] = s.paused[i], None
        if saved is None:
            return OK
        goal, motion, check, radius_m, phase, left_s, mission_state = saved
        s.set_goal(i, goal, Motion(motion), Check(check), radius_m, phase)
        if check == Check.TIMER:
            s.until_t_s[i] = s.t_s + left_s
        s.mission_state[i] = mission_state
        s.text(i, "Resumed")
        return OK

    def set_servo(self, i: int, channel: int, pwm: int) -> CommandOutcome:
        """DO_SET_SERVO: remembered (and acknowledged) as ArduCopter does; outputs 1-4 drive the motors."""
        s = self.s
        if not 1 <= channel <= 32 or not 0 <= pwm <= 65535:
            return CommandOutcome(Result.DENIED, f"Servo {channel} PWM {pwm} out of range")
        if channel <= 4:
            return CommandOutcome(Result.FAILED, f"Servo {channel} is a motor output")
        s.servo_pwm[i][channel] = pwm
        return OK

    def set_home(self, i: int, home_m: np.ndarray | None) -> CommandOutcome:
        """DO_SET_HOME: here (None) or a given place. RTL, relative altitudes and HOME_POSITION follow home; the
        local frame's origin (ArduPilot's EKF origin) stays, and with it LOCAL_POSITION_NED."""
        s = self.s
        if home_m is None:
            if not s.gps_ok[i]:
                return CommandOutcome(Result.FAILED, "Set home refused: no position")
            home_m = s.pos(i)
        home_m = np.asarray(home_m, dtype=float)
        if not np.isfinite(home_m).all() or np.hypot(*home_m[:2]) > HOME_FROM_ORIGIN_MAX_M:
            return CommandOutcome(Result.FAILED, "Set home refused: more than 50 km from the EKF origin")
        s.home_m[i] = home_m
        s.home_locked[i] = True
        s.emit(i, Event.HOME, None)
        return OK

    def enable_fence(self, i: int, enable: float) -> CommandOutcome:
        """DO_FENCE_ENABLE: 0 off, 1 on (2, floor only, is a plane's)."""
        s = self.s
        if enable not in (0, 1):
            return CommandOutcome(Result.DENIED, f"Fence enable {enable}: 0 or 1")
        s.params.set(i, "FENCE_ENABLE", enable)
        s.text(i, "Fence enabled" if enable else "Fence disabled")
        return OK
