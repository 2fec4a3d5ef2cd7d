"""Flight logic of every simulated autopilot (pure): `Autopilots`, the N vehicles' shared flight state and the
parts that act on it, stepped once after every physics step.

The parts, each over the one `FlightState` (sitl.vehicle.flight_state):
  mission_run  mission execution: installing a mission, sequencing its items, the return to launch
  modes        arming, flight modes, takeoff, mission start, reboot
  actions      GUIDED goals and setpoints, speed, heading, ROI, pause, servos, home, the fence switch
  guards       geofence, battery and GPS failsafes, auto-disarm
  pilot_input  RC overrides and the sticks in the pilot modes
`Autopilots` runs the per-step work (moving targets, completion checks, what a completed goal leads to, the
guards) and is the one entry the world and the MAVLink layer call. Arrays are per vehicle; completion checks
run vectorised each step and only vehicles with something to do (item reached, landed, timer expired) enter
Python. Results are MAV_RESULT numbers, events are plain tuples the MAVLink layer turns into messages.
"""

from __future__ import annotations

import numpy as np

from missions.geo import Home
from missions.model import MissionItem, MissionType
from sitl.vehicle import mission_items as items_
from sitl.vehicle import smart_rtl
from sitl.vehicle.actions import Actions
from sitl.vehicle.flight_state import (
    FORCE_DISARM_MAGIC,
    OK,
    Check,
    CommandOutcome,
    CopterMode,
    Event,
    FlightState,
    MissionState,
    Phase,
    Result,
    Severity,
)
from sitl.vehicle.guards import Guards
from sitl.vehicle.guided import Setpoint
from sitl.vehicle.mission_run import MissionRun
from sitl.vehicle.modes import Modes
from sitl.vehicle.params import ParamTable
from sitl.vehicle.physics import Motion, VehicleState
from sitl.vehicle.pilot_input import PilotInput

# ArduCopter's land detector: landed after this long descending no more than 0.2 m/s with low throttle, and the
# landing modes disarm then (land_detector.cpp LAND_DETECTOR_TRIGGER_SEC; mode_land.cpp, mode_rtl.cpp land_run)
LAND_DETECTOR_TRIGGER_S = 1.0

__all__ = [  # with the vocabulary (defined in flight_state) its users import from here
    "FORCE_DISARM_MAGIC", "OK", "Autopilots", "Check", "CommandOutcome", "CopterMode", "Event", "MissionState",
    "Phase", "Result", "Severity",
]


class Autopilots(FlightState):
    """The flight logic of N simulated autopilots: their shared flight state, the parts that act on it, the
    per-step update; positions are ENU metres about each vehicle's own home."""

    def __init__(self, homes: list[Home], params: ParamTable):
        super().__init__(homes, params)
        self.actions = Actions(self)
        self.mission_run = MissionRun(self, self.actions)
        self.modes = Modes(self, self.mission_run)
        self.guards = Guards(self, self.modes)
        self.pilot_input = PilotInput(self)

    # ---- per-step -------------------------------------------------------------------------------------
    def update(self, state: VehicleState, t_s: float) -> None:
        """Run completion checks and failsafes after a physics step."""
        dt_s = max(0.0, t_s - self.t_s)
        self.state, self.t_s = state, t_s
        check = self.check
        if not check.any() and not self.armed.any():
            return
        self._steer(state, dt_s)
        if self.armed.any() and int(t_s / smart_rtl.RECORD_PERIOD_S) != int((t_s - dt_s) / smart_rtl.RECORD_PERIOD_S):
            smart_rtl.record(self, state)
        pos = state.pos_m
        done = (check == Check.REACH) & (np.linalg.norm(pos - self.goal_m, axis=1) <= self.radius_m)
        done |= (check == Check.ALTITUDE) & (pos[:, 2] >= self.goal_m[:, 2] - self.alt_tolerance_m())
        done |= (check == Check.LANDED) & state.on_ground
        done |= (check == Check.TIMER) & (t_s >= self.until_t_s)
        for i in np.flatnonzero(done):
            self._on_done(int(i))
        self.guards.check(state, t_s)

    def _steer(self, state: VehicleState, dt_s: float) -> None:
        """Targets that move every step: velocity by commanded acceleration, loiter turns, the nose on an ROI."""
        velocity_control = self.motion == Motion.VELOCITY
        if velocity_control.any():
            accelerating = velocity_control & self.accel_mps2.any(axis=1)
            self.velocity_mps[accelerating] += self.accel_mps2[accelerating] * dt_s
        if self.circling:
            self.mission_run.circle(state)
        if self.rc_overridden.any():
            self.pilot_input.fly_sticks(state)
        looking = ~np.isnan(self.roi_m[:, 0])
        if looking.any():
            to_roi = self.roi_m[looking] - state.pos_m[looking]
            far = np.hypot(to_roi[:, 0], to_roi[:, 1]) > 1.0  # overhead the bearing means nothing: keep heading
            self.yaw_target_rad[np.flatnonzero(looking)[far]] = np.arctan2(to_roi[far, 0], to_roi[far, 1])

    def _on_done(self, i: int) -> None:
        """Vehicle i's goal check passed: what comes next depends on the phase it was in."""
        phase = self.phase[i]
        self.check[i] = Check.NONE
        if phase == Phase.TAKEOFF:
            self.text(i, "Takeoff complete")
        elif phase == Phase.MISSION:
            self.mission_run.item_reached(i)
        elif phase == Phase.MISSION_HOLD:  # reached a waypoint with a hold time / NAV_LOITER_TIME
            item = self.missions[i][MissionType.MISSION][self.current_seq[i]]
            self.timer(i, items_.holds_s(item), Phase.MISSION)
        elif phase == Phase.SMART_RTL:
            smart_rtl.next_point(self, i)
        elif phase == Phase.TURNS_ENTER:
            self.mission_run.start_circle(i)
        elif phase == Phase.RTL_CLIMB:
            east, north = self.rtl_target_m[i][:2]
            self.set_goal(i, [east, north, self.goal_m[i, 2]], Motion.GOTO, Check.REACH, self.wp_radius_m(i),
                          Phase.RTL_RETURN)
        elif phase == Phase.RTL_RETURN:
            east, north = self.rtl_target_m[i][:2]
            self.set_goal(i, [east, north, 0.0], Motion.LAND, Check.LANDED, phase=Phase.LAND)
        elif phase == Phase.LAND:
            if self.mode[i] == CopterMode.AUTO:
                self.mission_run.item_reached(i)
            self.text(i, "Landed")
            # LAND, RTL and a mission's NAV_LAND disarm once the land detector has seen the vehicle still for its
            # trigger time (DISARM_DELAY is for a vehicle left armed on the ground in the other modes)
            self.timer(i, LAND_DETECTOR_TRIGGER_S, Phase.DISARM_WAIT)
        elif phase == Phase.VELOCITY:
            self.text(i, "Guided: no velocity setpoint for 3 s, stopping", Severity.WARNING)
            self.hold(i)
        elif phase == Phase.DISARM_WAIT:
            if self.state is not None and self.state.on_ground[i] and self.armed[i]:
                self.disarm(i, "Auto-disarmed after landing")

    def on_params_changed(self) -> None:
        """A new WPNAV_SPEED applies at once; a mission's DO_CHANGE_SPEED below it stays while in AUTO."""
        limits = self.params.column("WPNAV_SPEED") / 100.0
        in_auto = self.mode == CopterMode.AUTO
        self.speed_xy_mps = np.where(in_auto, np.minimum(self.speed_xy_mps, limits), limits)

    # ---- what the world and the MAVLink layer ask (each part's entry points) ---------------------------
    def arm(self, i: int, arm: bool, force: bool = False) -> CommandOutcome:
        return self.modes.arm(i, arm, force)

    def prearm_failure(self, i: int) -> str | None:
        return self.modes.prearm_failure(i)

    def set_mode(self, i: int, mode: int) -> CommandOutcome:
        return self.modes.set_mode(i, mode)

    def takeoff(self, i: int, alt_m: float) -> CommandOutcome:
        return self.modes.takeoff(i, alt_m)

    def mission_start(self, i: int, first_seq: int) -> CommandOutcome:
        return self.modes.mission_start(i, first_seq)

    def reboot(self, i: int) -> CommandOutcome:
        return self.modes.reboot(i)

    def replace_mission(self, i: int, mission_type: int, items: list[MissionItem]) -> None:
        self.mission_run.replace_mission(i, mission_type, items)

    def set_current(self, i: int, seq: int) -> CommandOutcome:
        return self.mission_run.set_current(i, seq)

    def change_speed(self, i: int, speed_mps: float) -> CommandOutcome:
        return self.actions.change_speed(i, speed_mps)

    def goto(self, i: int, goal_m) -> CommandOutcome:
        return self.actions.goto(i, goal_m)

    def setpoint(self, i: int, target: Setpoint) -> bool:
        return self.actions.setpoint(i, target)

    def condition_yaw(self, i: int, angle_deg: float, speed_dps: float, direction: float,
                      relative: bool) -> CommandOutcome:
        return self.actions.condition_yaw(i, angle_deg, speed_dps, direction, relative)

    def set_roi(self, i: int, roi_m) -> CommandOutcome:
        return self.actions.set_roi(i, roi_m)

    def pause(self, i: int, pause: bool) -> CommandOutcome:
        return self.actions.pause(i, pause)

    def set_servo(self, i: int, channel: int, pwm: int) -> CommandOutcome:
        return self.actions.set_servo(i, channel, pwm)

    def set_home(self, i: int, home_m: np.ndarray | None) -> CommandOutcome:
        return self.actions.set_home(i, home_m)

    def enable_fence(self, i: int, enable: float) -> CommandOutcome:
        return self.actions.enable_fence(i, enable)

    def rc_override(self, i: int, values: list[int]) -> None:
        self.pilot_input.rc_override(i, values)
