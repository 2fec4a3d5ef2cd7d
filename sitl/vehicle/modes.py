"""Flight modes of the simulated autopilots (pure): arming and its pre-arm checks, entering a mode (hold, AUTO,
RTL, LAND), takeoff, mission start and the state a reboot leaves.

Modes are ArduCopter's custom_mode numbers (CopterMode). AUTO resumes the mission through mission_run; every
other mode sets its goal on the shared flight state.
"""

from __future__ import annotations

import math

import numpy as np

from sitl.vehicle import mission_items as items_
from sitl.vehicle import smart_rtl
from sitl.vehicle.flight_state import (
    HOLD_MODES,
    NOT_FLOWN_MODES,
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
from sitl.vehicle.mission_run import MissionRun
from sitl.vehicle.physics import Motion

AUTO_ALLOW_ARMING = 1  # ArduCopter's AUTO_OPTIONS bit 0 (mode_auto.cpp allows_arming)


class Modes:
    """Arming and flight modes of N autopilots over their shared flight state."""

    def __init__(self, s: FlightState, mission_run: MissionRun):
        self.s = s
        self.mission_run = mission_run  # AUTO flies the mission, RTL its return

    def arm(self, i: int, arm: bool, force: bool = False) -> CommandOutcome:
        """COMPONENT_ARM_DISARM: arming passes the pre-arm checks (force skips them) and puts home here; a
        flying vehicle disarms only when forced."""
        s = self.s
        if not arm:
            if not s.armed[i]:
                return OK
            if s.flying(i) and not force:
                return CommandOutcome(Result.DENIED, "Disarm refused: vehicle is flying")
            s.disarm(i, "Disarmed")
            return OK
        if s.armed[i]:
            return OK
        if s.transfer_busy[i]:
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Arm refused: mission transfer in progress")
        if not force:
            failure = self.prearm_failure(i)
            if failure:
                return CommandOutcome(Result.FAILED, failure)
            if s.mode[i] in (CopterMode.RTL, CopterMode.LAND):
                return CommandOutcome(Result.FAILED, f"Arm: mode {CopterMode(s.mode[i]).name} does not allow arming")
            if s.mode[i] == CopterMode.AUTO and not int(s.params.get(i, "AUTO_OPTIONS")) & AUTO_ALLOW_ARMING:
                return CommandOutcome(Result.FAILED, "Arm: mode AUTO needs AUTO_OPTIONS bit 0")  # 50 chars at most
        s.armed[i] = True
        smart_rtl.start_trail(s, i)
        s.failsafe[i] = False
        s.set_goal(i, s.pos(i), Motion.IDLE, Check.NONE)
        s.text(i, "Arming motors")
        s.emit(i, Event.ARMED, True)
        if not s.home_locked[i] and s.gps_ok[i]:  # ArduCopter: home is where it arms, unless DO_SET_HOME
            s.home_m[i] = s.pos(i)
            s.emit(i, Event.HOME, None)
        return OK

    def prearm_failure(self, i: int) -> str | None:
        """Why vehicle i fails its pre-arm checks (the SYS_STATUS PREARM_CHECK health), or None; ARMING_CHECK = 0
        skips them as on ArduCopter."""
        s = self.s
        if s.params.get(i, "ARMING_CHECK") == 0:
            return None
        if not s.gps_ok[i]:
            return "PreArm: GPS: no fix"
        if s.state is not None and s.state.soc[i] * 100.0 < s.params.get(i, "BATT_LOW_PCT"):
            return "PreArm: Battery below failsafe level"
        return None

    def set_mode(self, i: int, mode: int) -> CommandOutcome:
        """Enter a flight mode: hold where the vehicle is, or resume the mission (AUTO), return (RTL), land."""
        s = self.s
        try:
            mode = CopterMode(mode)
        except ValueError:
            name = NOT_FLOWN_MODES.get(mode, f"mode {mode}")
            return CommandOutcome(Result.DENIED, f"Mode change failed: {name} not in this SITL")
        previous = s.mode[i]
        s.mode[i] = mode
        s.srtl_route.pop(i, None)
        s.yaw_target_rad[i] = s.yaw_rate_rps[i] = math.nan
        s.roi_m[i] = math.nan
        s.paused[i] = None
        s.piloted[i] = False
        if mode in HOLD_MODES:
            s.hold(i)
        elif mode == CopterMode.AUTO:
            if s.armed[i] and len(s.mission(i)) > 1:
                seq = int(s.current_seq[i])
                if s.mission_state[i] == MissionState.COMPLETE or not 1 <= seq < len(s.mission(i)):
                    seq = 1
                self.mission_run.start_item(i, seq)
            else:
                s.hold(i)
        elif mode == CopterMode.RTL:
            if s.flying(i):
                self.mission_run.begin_rtl(i)
            else:
                s.hold(i)
        elif mode == CopterMode.CIRCLE:
            self._circle(i)
        elif mode == CopterMode.SMART_RTL:
            if not smart_rtl.begin(s, i):  # no trail: RTL, and the mode reported is RTL, as ArduCopter's fallback
                s.mode[i] = CopterMode.RTL
                self.mission_run.begin_rtl(i)
        elif mode == CopterMode.LAND:
            if s.flying(i):
                here = s.pos(i)
                s.set_goal(i, [here[0], here[1], 0.0], Motion.LAND, Check.LANDED, phase=Phase.LAND)
            else:
                s.hold(i)
        if previous != s.mode[i]:
            s.emit(i, Event.MODE, int(s.mode[i]))
        return OK

    def _circle(self, i: int) -> None:
        """ArduCopter's CIRCLE: round a centre CIRCLE_RADIUS ahead of the vehicle's heading, at CIRCLE_RATE
        (clockwise when positive), at the altitude it had, until another mode; on the ground it waits."""
        s = self.s
        if not s.flying(i):
            s.hold(i)
            return
        radius_m = s.params.get(i, "CIRCLE_RADIUS") / 100.0
        here, yaw = s.pos(i), float(s.state.yaw_rad[i])
        center = here + radius_m * np.array([math.sin(yaw), math.cos(yaw), 0.0])
        s.set_goal(i, here, Motion.VELOCITY, Check.NONE)
        if radius_m > 0:
            signed_m = math.copysign(radius_m, s.params.get(i, "CIRCLE_RATE") or 1.0)
            s.circling[i] = [center, signed_m, math.inf, items_.angle_about(here, center)]

    def takeoff(self, i: int, alt_m: float) -> CommandOutcome:
        """NAV_TAKEOFF: climb to alt_m above home in GUIDED (0 or NaN: PILOT_TKOFF_ALT)."""
        s = self.s
        if not math.isfinite(alt_m) or alt_m <= 0:
            default_cm = s.params.get(i, "PILOT_TKOFF_ALT")
            if default_cm <= 0:
                return CommandOutcome(Result.DENIED, f"Takeoff refused: altitude {alt_m} m must be above 0")
            alt_m = default_cm / 100.0
        if alt_m > 1000:
            return CommandOutcome(Result.DENIED, f"Takeoff refused: altitude {alt_m} m above 1000 m")
        if not s.armed[i]:
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Takeoff refused: arm first")
        if s.flying(i):
            return CommandOutcome(Result.FAILED, "Takeoff refused: already flying")
        if s.mode[i] != CopterMode.GUIDED:
            s.mode[i] = CopterMode.GUIDED
            s.emit(i, Event.MODE, int(CopterMode.GUIDED))
        here = s.pos(i)
        s.set_goal(i, [here[0], here[1], alt_m], Motion.GOTO, Check.ALTITUDE, phase=Phase.TAKEOFF)
        return OK

    def mission_start(self, i: int, first_seq: int) -> CommandOutcome:
        """MISSION_START: AUTO from item first_seq (0: where the mission stands, from 1 once complete)."""
        s = self.s
        items = s.mission(i)
        if len(items) <= 1:
            return CommandOutcome(Result.FAILED, "Mission start refused: no mission")
        if not s.armed[i]:
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Mission start refused: arm first")
        if first_seq >= len(items):
            return CommandOutcome(Result.DENIED, f"Mission start refused: item {first_seq} of {len(items) - 1}")
        if first_seq >= 1:
            s.current_seq[i] = first_seq
        elif s.mission_state[i] == MissionState.COMPLETE:
            s.current_seq[i] = 1
        s.jumps_left[i] = {}
        s.mode[i] = CopterMode.GUIDED  # forces the AUTO entry below to (re)start the item
        return self.set_mode(i, CopterMode.AUTO)

    def reboot(self, i: int) -> CommandOutcome:
        """What a restart leaves: missions and parameters (stored), nothing in flight; disarmed only."""
        s = self.s
        if s.armed[i]:
            return CommandOutcome(Result.FAILED, "Reboot refused: disarm first")
        s.mode[i] = CopterMode.STABILIZE
        s.set_goal(i, s.pos(i), Motion.IDLE, Check.NONE)
        s.failsafe[i] = False
        s.yaw_target_rad[i] = s.yaw_rate_rps[i] = math.nan
        s.roi_m[i] = math.nan
        s.home_locked[i] = False
        s.paused[i] = None
        s.speed_xy_mps[i] = s.params.get(i, "WPNAV_SPEED") / 100.0
        if len(s.mission(i)) > 1:
            s.current_seq[i] = 1
            s.mission_state[i] = MissionState.NOT_STARTED
        return OK
