"""Flight logic of every simulated autopilot: modes, commands, mission execution, failsafes (pure).

Arrays are per vehicle; completion checks run vectorised each step and only vehicles with something to do
(item reached, landed, timer expired) enter Python. Results are MAV_RESULT numbers, events are plain tuples
the MAVLink layer turns into messages. Mission item 0 is home, as on ArduPilot: execution starts at seq 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum, IntEnum

import numpy as np

from missions.geo import Home, lla_to_enu
from missions.model import AMSL_FRAMES, MavCmd, MissionItem, MissionType
from sitl.vehicle import fence as fence_
from sitl.vehicle import mission_items as items_
from sitl.vehicle import pilot
from sitl.vehicle.guided import VELOCITY_TIMEOUT_S, Setpoint
from sitl.vehicle.params import ParamTable
from sitl.vehicle.physics import Command, Motion, VehicleState


class Result(IntEnum):
    """MAV_RESULT."""

    ACCEPTED = 0
    TEMPORARILY_REJECTED = 1
    DENIED = 2
    UNSUPPORTED = 3
    FAILED = 4
    IN_PROGRESS = 5


class CopterMode(IntEnum):
    """ArduCopter custom_mode numbers, so pymavlink, MAVProxy and QGC name them."""

    STABILIZE = 0
    ALT_HOLD = 2
    AUTO = 3
    GUIDED = 4
    LOITER = 5
    RTL = 6
    LAND = 9
    POSHOLD = 16
    BRAKE = 17


class MissionState(IntEnum):
    """MISSION_STATE (MISSION_CURRENT.mission_state)."""

    NO_MISSION = 1
    NOT_STARTED = 2
    ACTIVE = 3
    PAUSED = 4
    COMPLETE = 5


class Severity(IntEnum):
    """MAV_SEVERITY of the texts the autopilot sends."""

    CRITICAL = 2
    ERROR = 3
    WARNING = 4
    INFO = 6


class Event(Enum):
    """What the flight logic tells the MAVLink layer to announce."""

    ITEM_REACHED = "item_reached"  # value: seq
    MISSION_CURRENT = "mission_current"  # value: seq
    MODE = "mode"  # value: custom mode number
    ARMED = "armed"  # value: bool
    TEXT = "text"  # value: (Severity, text)
    HOME = "home"  # value: None (home moved: HOME_POSITION is sent)


class Phase(Enum):
    """What the vehicle is doing toward its current goal; decides what happens when the goal's check passes."""

    NONE = "none"
    TAKEOFF = "takeoff"
    MISSION = "mission"  # flying to a mission item
    MISSION_HOLD = "mission_hold"  # flying to an item with a hold time, then waiting there
    RTL_CLIMB = "rtl_climb"
    RTL_RETURN = "rtl_return"
    LAND = "land"
    DISARM_WAIT = "disarm_wait"
    VELOCITY = "velocity"  # GUIDED velocity control: the timer is the setpoint's timeout
    TURNS_ENTER = "turns_enter"  # NAV_LOITER_TURNS: flying to the circle
    TURNS = "turns"  # ... going round it (velocity control, no timeout)
    LOITER_UNLIM = "loiter_unlim"  # NAV_LOITER_UNLIM: at its place until the mode or the item changes


class Check(IntEnum):
    NONE = 0
    REACH = 1  # within radius_m of goal (3D)
    ALTITUDE = 2  # climbed to the goal's altitude
    LANDED = 3  # touched down
    TIMER = 4  # sim time reached until_t


PILOT_MODES = frozenset({CopterMode.LOITER, CopterMode.POSHOLD, CopterMode.ALT_HOLD})
HOLD_MODES = frozenset({CopterMode.STABILIZE, CopterMode.ALT_HOLD, CopterMode.LOITER, CopterMode.POSHOLD,
                        CopterMode.BRAKE, CopterMode.GUIDED})
HOME_FROM_ORIGIN_MAX_M = 50_000.0  # ArduPilot refuses a home farther than this from the EKF origin
FORCE_DISARM_MAGIC = 21196  # COMPONENT_ARM_DISARM param 2: disarm even in flight (ArduPilot)


@dataclass(frozen=True)
class CommandOutcome:
    result: Result
    text: str = ""


OK = CommandOutcome(Result.ACCEPTED)


class Fleet:
    """Autopilot logic for N vehicles; positions are ENU metres about each vehicle's own home."""

    def __init__(self, homes: list[Home], params: ParamTable):
        n = len(homes)
        self.n = n
        self.homes = homes
        self.params = params
        self.mode = np.full(n, CopterMode.STABILIZE, dtype=int)
        self.armed = np.zeros(n, dtype=bool)
        self.motion = np.full(n, Motion.IDLE, dtype=int)
        self.goal_m = np.zeros((n, 3))
        self.speed_xy_mps = params.column("WPNAV_SPEED") / 100.0
        self.check = np.zeros(n, dtype=int)
        self.radius_m = np.zeros(n)
        self.until_t_s = np.full(n, math.inf)
        self.phase = [Phase.NONE] * n
        self.missions: list[dict[int, list[MissionItem]]] = [{t: [] for t in MissionType} for _ in range(n)]
        self.current_seq = np.zeros(n, dtype=int)
        self.mission_state = np.full(n, MissionState.NO_MISSION, dtype=int)
        self.jumps_left: list[dict[int, int]] = [{} for _ in range(n)]
        self.gps_ok = np.ones(n, dtype=bool)
        self.transfer_busy = np.zeros(n, dtype=bool)
        self.failsafe = np.zeros(n, dtype=bool)
        self.events: list[tuple[int, Event, object]] = []
        self.velocity_mps = np.zeros((n, 3))  # GUIDED velocity control target, ENU
        self.accel_mps2 = np.zeros((n, 3))  # ... and the acceleration that moves it
        self.yaw_target_rad = np.full(n, math.nan)  # commanded heading (NaN: face the direction of travel)
        self.yaw_rate_rps = np.full(n, math.nan)
        self.roi_m = np.full((n, 3), math.nan)  # region of interest the nose points at (DO_SET_ROI*), ENU
        self.circling: dict[int, list] = {}  # NAV_LOITER_TURNS: [centre, radius, turns left (rad), last bearing]
        self.rtl_target_m = np.zeros((n, 3))  # where RTL goes: home or the nearest rally point
        self.home_m = np.zeros((n, 3))  # home about the frame's origin (DO_SET_HOME moves home, not the origin)
        self.home_locked = np.zeros(n, dtype=bool)  # set by DO_SET_HOME: arming no longer moves home
        self.fences: list[fence_.Fence | None] = [None] * n  # built from the fence list when first needed
        self.fence_breach = np.full(n, None, dtype=object)  # why each vehicle is outside its fence, or None
        self.rc_us = np.tile(pilot.idle_channels(), (n, 1))  # RC_CHANNELS_OVERRIDE, else the idle receiver
        self.rc_overridden = np.zeros((n, pilot.CHANNELS), dtype=bool)
        self.rc_until_t_s = np.full(n, -math.inf)
        self.piloted = np.zeros(n, dtype=bool)  # flying on the sticks in a pilot mode
        self.idle_since_t_s = np.full(n, math.inf)  # armed, on the ground and not taking off, since
        self.paused: list[tuple | None] = [None] * n  # DO_PAUSE_CONTINUE: what to resume
        self.servo_pwm: list[dict[int, int]] = [{} for _ in range(n)]  # DO_SET_SERVO outputs (not simulated)
        self.t_s = 0.0
        self.state: VehicleState | None = None

    # ---- per-step -------------------------------------------------------------------------------------
    def command(self) -> Command:
        return Command(motion=self.motion, goal_m=self.goal_m, armed=self.armed, speed_xy_mps=self.speed_xy_mps,
                       velocity_mps=self.velocity_mps, yaw_target_rad=self.yaw_target_rad,
                       yaw_rate_rps=self.yaw_rate_rps)

    def update(self, state: VehicleState, t_s: float) -> None:
        """Run completion checks and failsafes after a physics step."""
        dt_s = max(0.0, t_s - self.t_s)
        self.state, self.t_s = state, t_s
        check = self.check
        if not check.any() and not self.armed.any():
            return
        self._steer(state, dt_s)
        pos = state.pos_m
        done = (check == Check.REACH) & (np.linalg.norm(pos - self.goal_m, axis=1) <= self.radius_m)
        done |= (check == Check.ALTITUDE) & (pos[:, 2] >= self.goal_m[:, 2] - self._alt_tolerance_m())
        done |= (check == Check.LANDED) & state.on_ground
        done |= (check == Check.TIMER) & (t_s >= self.until_t_s)
        for i in np.flatnonzero(done):
            self._on_done(int(i))
        self._auto_disarm(state, t_s)
        self._check_fences(state)
        flying = self.armed & ~state.on_ground
        low_batt = flying & ~self.failsafe & (state.soc * 100.0 < self.params.column("BATT_LOW_PCT"))
        no_gps = flying & ~self.gps_ok & (self.mode != CopterMode.LAND)
        for i in np.flatnonzero(low_batt | no_gps):
            self._failsafe(int(i), bool(no_gps[i]))

    def _steer(self, state: VehicleState, dt_s: float) -> None:
        """Targets that move every step: velocity by commanded acceleration, loiter turns, the nose on an ROI."""
        velocity_control = self.motion == Motion.VELOCITY
        if velocity_control.any():
            accelerating = velocity_control & self.accel_mps2.any(axis=1)
            self.velocity_mps[accelerating] += self.accel_mps2[accelerating] * dt_s
        if self.circling:
            self._circle(state)
        if self.rc_overridden.any():
            self._fly_sticks(state)
        looking = ~np.isnan(self.roi_m[:, 0])
        if looking.any():
            to_roi = self.roi_m[looking] - state.pos_m[looking]
            far = np.hypot(to_roi[:, 0], to_roi[:, 1]) > 1.0  # overhead the bearing means nothing: keep heading
            self.yaw_target_rad[np.flatnonzero(looking)[far]] = np.arctan2(to_roi[far, 0], to_roi[far, 1])

    def _check_fences(self, state: VehicleState) -> None:
        """FENCE_ENABLE: a flying vehicle that leaves the fence says so and takes FENCE_ACTION (0 report only,
        2 land, 4 brake, otherwise RTL); coming back inside clears the breach."""
        watched = self.armed & ~state.on_ground & (self.params.column("FENCE_ENABLE") > 0)
        for i in np.flatnonzero(watched | np.not_equal(self.fence_breach, None)):
            i = int(i)
            reason = fence_.breach(self._fence(i), state.pos_m[i], int(self.params.get(i, "FENCE_TYPE")),
                                   self.params.get(i, "FENCE_ALT_MAX"), self.params.get(i, "FENCE_RADIUS")) \
                if watched[i] else None
            if reason is None:
                if self.fence_breach[i] is not None:
                    self.fence_breach[i] = None
                    self._text(i, "Fence breach cleared")
                continue
            if self.fence_breach[i] is not None:
                continue
            self.fence_breach[i] = reason
            self._text(i, f"Fence breached: {reason}", Severity.CRITICAL)
            action = int(self.params.get(i, "FENCE_ACTION"))
            if action == 0 or self.mode[i] in (CopterMode.RTL, CopterMode.LAND):
                continue
            self.set_mode(i, {2: CopterMode.LAND, 4: CopterMode.BRAKE}.get(action, CopterMode.RTL))

    def _fence(self, i: int) -> fence_.Fence:
        if self.fences[i] is None:
            self.fences[i] = fence_.fence_from_items(self.mission(i, MissionType.FENCE), self.homes[i])
        return self.fences[i]

    def enable_fence(self, i: int, enable: float) -> CommandOutcome:
        """DO_FENCE_ENABLE: 0 off, 1 on (2, floor only, is a plane's)."""
        if enable not in (0, 1):
            return CommandOutcome(Result.DENIED, f"Fence enable {enable}: 0 or 1")
        self.params.set(i, "FENCE_ENABLE", enable)
        self._text(i, "Fence enabled" if enable else "Fence disabled")
        return OK

    def _auto_disarm(self, state: VehicleState, t_s: float) -> None:
        """ArduCopter's DISARM_DELAY: a vehicle armed on the ground that does not take off disarms itself."""
        idle = self.armed & state.on_ground & (self.motion == Motion.IDLE)
        self.idle_since_t_s[~idle] = math.inf
        self.idle_since_t_s[idle & np.isinf(self.idle_since_t_s)] = t_s
        delay_s = self.params.column("DISARM_DELAY")
        for i in np.flatnonzero(idle & (delay_s > 0) & (t_s - self.idle_since_t_s >= delay_s)):
            self._disarm(int(i), f"Auto-disarmed: armed on the ground for {delay_s[i]:g} s")

    def _alt_tolerance_m(self) -> np.ndarray:
        return np.clip(0.1 * self.goal_m[:, 2], 0.1, 0.5)

    def _emit(self, i: int, kind: Event, value: object = None) -> None:
        self.events.append((i, kind, value))

    def _text(self, i: int, text: str, severity: Severity = Severity.INFO) -> None:
        self._emit(i, Event.TEXT, (severity, text))

    def _pos(self, i: int) -> np.ndarray:
        assert self.state is not None
        return self.state.pos_m[i].copy()

    def _flying(self, i: int) -> bool:
        return bool(self.armed[i] and self.state is not None and not self.state.on_ground[i])

    def _set_goal(self, i: int, goal_m, motion: Motion, check: Check, radius_m: float = 0.0, phase: Phase = Phase.NONE):
        self.circling.pop(i, None)
        self.goal_m[i] = goal_m
        self.motion[i] = motion
        self.check[i] = check
        self.radius_m[i] = radius_m
        self.phase[i] = phase

    def _hold(self, i: int) -> None:
        if self._flying(i):
            self._set_goal(i, self._stopping_point_m(i), Motion.GOTO, Check.NONE)
        else:
            self._set_goal(i, self._pos(i), Motion.IDLE, Check.NONE)

    def _stopping_point_m(self, i: int) -> np.ndarray:
        """Where a stop ends: here under the research's law; ahead by v^2 / 2a under ArduCopter's, which brakes
        to that point rather than turning back to where the stop was asked."""
        here = self._pos(i)
        if self.params.get(i, "NAC_NAV_LAW") == 1 or self.state is None:
            return here
        velocity = self.state.vel_mps[i]
        accel_xy = self.params.get(i, "WPNAV_ACCEL") / 100.0
        accel_z = self.params.get(i, "WPNAV_ACCEL_Z") / 100.0
        here[:2] += velocity[:2] * float(np.hypot(*velocity[:2])) / (2.0 * accel_xy)
        here[2] = max(here[2] + velocity[2] * abs(velocity[2]) / (2.0 * accel_z), 0.5)
        return here

    def _timer(self, i: int, seconds: float, phase: Phase) -> None:
        self.check[i] = Check.TIMER
        self.until_t_s[i] = self.t_s + seconds
        self.phase[i] = phase

    # ---- completion -----------------------------------------------------------------------------------
    def _on_done(self, i: int) -> None:
        phase = self.phase[i]
        self.check[i] = Check.NONE
        if phase == Phase.TAKEOFF:
            self._text(i, "Takeoff complete")
        elif phase == Phase.MISSION:
            self._item_reached(i)
        elif phase == Phase.MISSION_HOLD:  # reached a waypoint with a hold time / NAV_LOITER_TIME
            item = self.missions[i][MissionType.MISSION][self.current_seq[i]]
            self._timer(i, items_.holds_s(item), Phase.MISSION)
        elif phase == Phase.TURNS_ENTER:
            self._start_circle(i)
        elif phase == Phase.RTL_CLIMB:
            east, north = self.rtl_target_m[i][:2]
            self._set_goal(i, [east, north, self.goal_m[i, 2]], Motion.GOTO, Check.REACH, self._wp_radius_m(i),
                           Phase.RTL_RETURN)
        elif phase == Phase.RTL_RETURN:
            east, north = self.rtl_target_m[i][:2]
            self._set_goal(i, [east, north, 0.0], Motion.LAND, Check.LANDED, phase=Phase.LAND)
        elif phase == Phase.LAND:
            if self.mode[i] == CopterMode.AUTO:
                self._item_reached(i)
            self._text(i, "Landed")
            self._timer(i, self.params.get(i, "DISARM_DELAY"), Phase.DISARM_WAIT)
        elif phase == Phase.VELOCITY:
            self._text(i, "Guided: no velocity setpoint for 3 s, stopping", Severity.WARNING)
            self._hold(i)
        elif phase == Phase.DISARM_WAIT:
            if self.state is not None and self.state.on_ground[i] and self.armed[i]:
                self._disarm(i, "Auto-disarmed after landing")

    def _failsafe(self, i: int, gps: bool) -> None:
        self.failsafe[i] = True
        if gps:
            self._text(i, "EKF failsafe: GPS lost, landing", Severity.CRITICAL)
            self.set_mode(i, CopterMode.LAND)
            return
        action = int(self.params.get(i, "BATT_FS_LOW_ACT"))
        self._text(i, "Battery failsafe: low battery", Severity.CRITICAL)
        if action == 2:
            self.set_mode(i, CopterMode.RTL)
        elif action == 1:
            self.set_mode(i, CopterMode.LAND)

    # ---- missions -------------------------------------------------------------------------------------
    def mission(self, i: int, mission_type: int = MissionType.MISSION) -> list[MissionItem]:
        return self.missions[i][MissionType(mission_type)]

    def replace_mission(self, i: int, mission_type: int, items: list[MissionItem]) -> None:
        """Install a complete, validated list (seq 0..n-1); only called once a transfer has succeeded."""
        self.missions[i][MissionType(mission_type)] = items
        if mission_type == MissionType.FENCE:
            self.fences[i] = None
        if mission_type != MissionType.MISSION:
            return
        self.jumps_left[i] = {}
        if len(items) <= 1:
            self.current_seq[i] = 0
            self.mission_state[i] = MissionState.NO_MISSION
            if self.mode[i] == CopterMode.AUTO:
                self._hold(i)
        else:
            if not 1 <= self.current_seq[i] < len(items):
                self.current_seq[i] = 1
            running = self.mode[i] == CopterMode.AUTO and self.armed[i]
            self.mission_state[i] = MissionState.ACTIVE if running else MissionState.NOT_STARTED
            if running:
                self._start_item(i, int(self.current_seq[i]))
        self._emit(i, Event.MISSION_CURRENT, int(self.current_seq[i]))

    def _wp_radius_m(self, i: int) -> float:
        return self.params.get(i, "WPNAV_RADIUS") / 100.0

    def item_goal_m(self, i: int, item: MissionItem) -> np.ndarray:
        here = self._pos(i)
        if item.lat_deg == 0.0 and item.lon_deg == 0.0:
            goal = here.copy()
        else:
            goal = lla_to_enu(item.lat_deg, item.lon_deg, self.homes[i].alt_m, self.homes[i])
        if item.frame in AMSL_FRAMES:
            goal[2] = item.alt_m - self.homes[i].alt_m
        else:
            goal[2] = item.alt_m + self.home_m[i, 2]
        goal[2] = max(goal[2], 0.0)
        return goal

    def _item_reached(self, i: int) -> None:
        seq = int(self.current_seq[i])
        self._emit(i, Event.ITEM_REACHED, seq)
        self._start_item(i, seq + 1)

    def _start_item(self, i: int, seq: int) -> None:
        items = self.mission(i)
        for _ in range(4 * len(items) + 2):  # bounds DO_JUMP chains that never reach a nav item
            if seq >= len(items):
                self._mission_complete(i)
                return
            item = items[seq]
            if self.current_seq[i] != seq:
                self.current_seq[i] = seq
                self._emit(i, Event.MISSION_CURRENT, seq)
            self.mission_state[i] = MissionState.ACTIVE
            cmd = item.command
            if cmd in (MavCmd.DO_JUMP, items_.DO_JUMP_TAG):
                seq = self._jump(i, seq, item)
                continue
            if cmd in items_.DO_ACTED or cmd in items_.DO_NO_EFFECT:
                self._do(i, item)
                self._emit(i, Event.ITEM_REACHED, seq)
                seq += 1
                continue
            self._start_nav_item(i, item)
            return
        self._text(i, "Mission: DO_JUMP loop without a navigation command, stopping", Severity.ERROR)
        self._mission_complete(i)

    def _jump(self, i: int, seq: int, item: MissionItem) -> int:
        """The item after a DO_JUMP (to a seq) or DO_JUMP_TAG (to the JUMP_TAG with that number), counting its
        repeats (-1: for ever)."""
        items = self.mission(i)
        if item.command == MavCmd.DO_JUMP:
            target = int(item.p1)
        else:
            target = next((k for k, it in enumerate(items) if it.command == items_.JUMP_TAG and it.p1 == item.p1), -1)
        left = self.jumps_left[i].setdefault(seq, int(item.p2))
        if left == 0 or not 1 <= target < len(items):
            return seq + 1
        if left > 0:
            self.jumps_left[i][seq] = left - 1
        return target

    def _do(self, i: int, item: MissionItem) -> None:
        """A DO or CONDITION item of a running mission (those with no effect here are passed over)."""
        cmd = item.command
        if cmd == MavCmd.DO_CHANGE_SPEED:
            if item.p2 > 0:
                self.speed_xy_mps[i] = item.p2
        elif cmd == MavCmd.CONDITION_YAW:
            self.condition_yaw(i, item.p1, item.p2, item.p3, item.p4 >= 0.5)
        elif cmd == items_.DO_SET_ROI_NONE or (cmd == items_.DO_SET_ROI and item.lat_deg == item.lon_deg == 0.0):
            self.set_roi(i, None)
        elif cmd in (items_.DO_SET_ROI, items_.DO_SET_ROI_LOCATION):
            self.set_roi(i, self.item_goal_m(i, item))
        elif cmd == items_.DO_SET_SERVO:
            self.set_servo(i, int(item.p1), int(item.p2))
        elif cmd == items_.DO_FENCE_ENABLE:
            self.enable_fence(i, item.p1)
        elif cmd == items_.DO_SET_HOME:
            self.set_home(i, None if item.p1 >= 0.5 else self.item_goal_m(i, item))

    def _start_nav_item(self, i: int, item: MissionItem) -> None:
        cmd = item.command
        goal = self.item_goal_m(i, item)
        here = self._pos(i)
        if cmd in items_.TAKEOFFS:
            self._set_goal(i, [here[0], here[1], max(goal[2], here[2])], Motion.GOTO, Check.ALTITUDE,
                           phase=Phase.MISSION)
        elif cmd in items_.LANDINGS:
            self._set_goal(i, [goal[0], goal[1], 0.0], Motion.LAND, Check.LANDED, phase=Phase.LAND)
        elif cmd == MavCmd.NAV_RETURN_TO_LAUNCH:
            self._begin_rtl(i)
        elif cmd == items_.NAV_DELAY:
            self._set_goal(i, here, Motion.GOTO if self._flying(i) else Motion.IDLE, Check.NONE)
            if item.p1 < 0:
                self._text(i, "NAV_DELAY until a time of day is not simulated: not waiting", Severity.WARNING)
            self._timer(i, max(0.0, item.p1) if math.isfinite(item.p1) else 0.0, Phase.MISSION)
        elif cmd == MavCmd.NAV_LOITER_TURNS:
            count, radius_m = items_.turns(item)
            outward = here[:2] - goal[:2]
            norm = float(np.hypot(*outward))
            edge = goal[:2] + (outward / norm if norm > 1e-6 else np.array([0.0, 1.0])) * abs(radius_m)
            self._set_goal(i, [edge[0], edge[1], goal[2]], Motion.GOTO, Check.REACH, self._wp_radius_m(i),
                           Phase.TURNS_ENTER)
        elif cmd == MavCmd.NAV_LOITER_UNLIM:
            self._set_goal(i, goal, Motion.GOTO, Check.NONE, phase=Phase.LOITER_UNLIM)
        else:
            radius = item.p2 if cmd == MavCmd.NAV_WAYPOINT and item.p2 > 0 else self._wp_radius_m(i)
            holds = cmd == MavCmd.NAV_LOITER_TIME or items_.holds_s(item) > 0
            self._set_goal(i, goal, Motion.GOTO, Check.REACH, radius, Phase.MISSION_HOLD if holds else Phase.MISSION)

    def _start_circle(self, i: int) -> None:
        item = self.mission(i)[self.current_seq[i]]
        count, radius_m = items_.turns(item)
        center = self.item_goal_m(i, item)
        self._set_goal(i, self._pos(i), Motion.VELOCITY, Check.NONE, phase=Phase.TURNS)
        self.circling[i] = [center, radius_m, 2 * math.pi * count, items_.angle_about(self._pos(i), center)]
        if count == 0:
            self.circling.pop(i)
            self._item_reached(i)

    def rc_override(self, i: int, values: list[int]) -> None:
        """RC_CHANNELS_OVERRIDE: the channels it sets hold for RC_OVERRIDE_TIME."""
        pilot.apply_override(self.rc_us[i], self.rc_overridden[i], values)
        self.rc_until_t_s[i] = self.t_s + pilot.OVERRIDE_TIMEOUT_S

    def _fly_sticks(self, state: VehicleState) -> None:
        """Pilot modes follow the sticks as velocity and yaw-rate commands; an override that times out is
        released and the copter holds where it is."""
        for i in np.flatnonzero(self.rc_overridden.any(axis=1)):
            i = int(i)
            if self.t_s >= self.rc_until_t_s[i]:
                self.rc_us[i], self.rc_overridden[i] = pilot.idle_channels(), False
                if self.piloted[i]:
                    self._text(i, "RC override timed out: holding", Severity.WARNING)
                    self.piloted[i] = False
                    self._hold(i)
                continue
            if not (self.armed[i] and self.mode[i] in PILOT_MODES):
                continue
            velocity, yaw_rate = pilot.stick_command(
                self.rc_us[i], bool(self.rc_overridden[i, 2]), float(state.yaw_rad[i]),
                self.params.get(i, "LOIT_SPEED") / 100.0, self.params.get(i, "PILOT_SPEED_UP") / 100.0,
                self.params.get(i, "PILOT_SPEED_DN") / 100.0)
            grounded = bool(state.on_ground[i]) and velocity[2] <= 0
            self.circling.pop(i, None)
            self.goal_m[i], self.check[i], self.phase[i] = state.pos_m[i], Check.NONE, Phase.NONE
            self.motion[i] = Motion.IDLE if grounded else Motion.VELOCITY
            self.velocity_mps[i], self.accel_mps2[i] = velocity, 0.0
            if yaw_rate:
                self.yaw_target_rad[i], self.yaw_rate_rps[i] = math.nan, yaw_rate
            elif math.isnan(self.yaw_target_rad[i]):  # the nose stays where the pilot left it
                self.yaw_target_rad[i], self.yaw_rate_rps[i] = float(state.yaw_rad[i]), math.nan
            self.piloted[i] = not grounded

    def _circle(self, state: VehicleState) -> None:
        """Loiter turns: steer each circling vehicle round its circle, count the angle it has gone round."""
        k_xy, k_z = self.params.column("NAC_KP_XY"), self.params.column("NAC_KP_Z")
        for i, circle in list(self.circling.items()):
            center, radius_m, left_rad, last = circle
            bearing = items_.angle_about(state.pos_m[i], center)
            turned = (bearing - last + math.pi) % (2 * math.pi) - math.pi
            circle[2] = left_rad - (turned if radius_m > 0 else -turned)
            circle[3] = bearing
            if circle[2] <= 0:
                del self.circling[i]
                self._item_reached(i)
                continue
            self.velocity_mps[i] = items_.circle_velocity_mps(state.pos_m[i], center, radius_m,
                                                              max(float(k_xy[i]), 0.5), float(k_z[i]))

    def _mission_complete(self, i: int) -> None:
        self.mission_state[i] = MissionState.COMPLETE
        self._emit(i, Event.MISSION_CURRENT, int(self.current_seq[i]))
        self._text(i, "Mission complete")
        if self.phase[i] != Phase.DISARM_WAIT:
            self._hold(i)

    # ---- commands -------------------------------------------------------------------------------------
    def arm(self, i: int, arm: bool, force: bool = False) -> CommandOutcome:
        if not arm:
            if not self.armed[i]:
                return OK
            if self._flying(i) and not force:
                return CommandOutcome(Result.DENIED, "Disarm refused: vehicle is flying")
            self._disarm(i, "Disarmed")
            return OK
        if self.armed[i]:
            return OK
        if self.transfer_busy[i]:
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Arm refused: mission transfer in progress")
        if not force:
            failure = self.prearm_failure(i)
            if failure:
                return CommandOutcome(Result.FAILED, failure)
            if self.mode[i] in (CopterMode.RTL, CopterMode.LAND):
                return CommandOutcome(Result.FAILED, f"Arm: mode {CopterMode(self.mode[i]).name} does not allow arming")
        self.armed[i] = True
        self.failsafe[i] = False
        self._set_goal(i, self._pos(i), Motion.IDLE, Check.NONE)
        self._text(i, "Arming motors")
        self._emit(i, Event.ARMED, True)
        if not self.home_locked[i] and self.gps_ok[i]:  # ArduCopter: home is where it arms, unless DO_SET_HOME
            self.home_m[i] = self._pos(i)
            self._emit(i, Event.HOME, None)
        return OK

    def prearm_failure(self, i: int) -> str | None:
        """Why vehicle i fails its pre-arm checks (the SYS_STATUS PREARM_CHECK health), or None; ARMING_CHECK = 0
        skips them as on ArduCopter."""
        if self.params.get(i, "ARMING_CHECK") == 0:
            return None
        if not self.gps_ok[i]:
            return "PreArm: GPS: no fix"
        if self.state is not None and self.state.soc[i] * 100.0 < self.params.get(i, "BATT_LOW_PCT"):
            return "PreArm: Battery below failsafe level"
        return None

    def _disarm(self, i: int, text: str) -> None:
        self.armed[i] = False
        self.idle_since_t_s[i] = math.inf
        self._set_goal(i, self._pos(i), Motion.IDLE, Check.NONE)
        if self.mode[i] == CopterMode.AUTO and self.mission_state[i] == MissionState.ACTIVE:
            self.mission_state[i] = MissionState.PAUSED
        self._text(i, text)
        self._emit(i, Event.ARMED, False)

    def set_mode(self, i: int, mode: int) -> CommandOutcome:
        try:
            mode = CopterMode(mode)
        except ValueError:
            return CommandOutcome(Result.DENIED, f"Mode change failed: unsupported mode {mode}")
        previous = self.mode[i]
        self.mode[i] = mode
        self.yaw_target_rad[i] = self.yaw_rate_rps[i] = math.nan
        self.roi_m[i] = math.nan
        self.paused[i] = None
        self.piloted[i] = False
        if mode in HOLD_MODES:
            self._hold(i)
        elif mode == CopterMode.AUTO:
            if self.armed[i] and len(self.mission(i)) > 1:
                seq = int(self.current_seq[i])
                if self.mission_state[i] == MissionState.COMPLETE or not 1 <= seq < len(self.mission(i)):
                    seq = 1
                self._start_item(i, seq)
            else:
                self._hold(i)
        elif mode == CopterMode.RTL:
            if self._flying(i):
                self._begin_rtl(i)
            else:
                self._hold(i)
        elif mode == CopterMode.LAND:
            if self._flying(i):
                here = self._pos(i)
                self._set_goal(i, [here[0], here[1], 0.0], Motion.LAND, Check.LANDED, phase=Phase.LAND)
            else:
                self._hold(i)
        if previous != mode:
            self._emit(i, Event.MODE, int(mode))
        return OK

    def _begin_rtl(self, i: int) -> None:
        """Climb to RTL_ALT, fly to the nearest rally point (or home), land there."""
        here = self._pos(i)
        rally = fence_.rally_target(self.mission(i, MissionType.RALLY), self.homes[i], self.home_m[i], here,
                                    self.params.get(i, "RALLY_INCL_HOME") > 0, self.params.get(i, "RALLY_LIMIT_KM"))
        self.rtl_target_m[i] = self.home_m[i] if rally is None else rally
        if rally is not None:
            self._text(i, f"RTL: to the rally point {np.hypot(*(rally[:2] - here[:2])):.0f} m away")
        rtl_alt = max(here[2], self.home_m[i, 2] + self.params.get(i, "RTL_ALT") / 100.0)
        self._set_goal(i, [here[0], here[1], rtl_alt], Motion.GOTO, Check.ALTITUDE, phase=Phase.RTL_CLIMB)

    def takeoff(self, i: int, alt_m: float) -> CommandOutcome:
        if not math.isfinite(alt_m) or alt_m <= 0:
            default_cm = self.params.get(i, "PILOT_TKOFF_ALT")
            if default_cm <= 0:
                return CommandOutcome(Result.DENIED, f"Takeoff refused: altitude {alt_m} m must be above 0")
            alt_m = default_cm / 100.0
        if alt_m > 1000:
            return CommandOutcome(Result.DENIED, f"Takeoff refused: altitude {alt_m} m above 1000 m")
        if not self.armed[i]:
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Takeoff refused: arm first")
        if self._flying(i):
            return CommandOutcome(Result.FAILED, "Takeoff refused: already flying")
        if self.mode[i] != CopterMode.GUIDED:
            self.mode[i] = CopterMode.GUIDED
            self._emit(i, Event.MODE, int(CopterMode.GUIDED))
        here = self._pos(i)
        self._set_goal(i, [here[0], here[1], alt_m], Motion.GOTO, Check.ALTITUDE, phase=Phase.TAKEOFF)
        return OK

    def mission_start(self, i: int, first_seq: int) -> CommandOutcome:
        items = self.mission(i)
        if len(items) <= 1:
            return CommandOutcome(Result.FAILED, "Mission start refused: no mission")
        if not self.armed[i]:
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Mission start refused: arm first")
        if first_seq >= len(items):
            return CommandOutcome(Result.DENIED, f"Mission start refused: item {first_seq} of {len(items) - 1}")
        if first_seq >= 1:
            self.current_seq[i] = first_seq
        elif self.mission_state[i] == MissionState.COMPLETE:
            self.current_seq[i] = 1
        self.jumps_left[i] = {}
        self.mode[i] = CopterMode.GUIDED  # forces the AUTO entry below to (re)start the item
        return self.set_mode(i, CopterMode.AUTO)

    def set_current(self, i: int, seq: int) -> CommandOutcome:
        items = self.mission(i)
        if not 0 <= seq < len(items):
            return CommandOutcome(Result.DENIED, f"Set current refused: no item {seq} (mission has {len(items)})")
        seq = max(seq, 1)
        self.current_seq[i] = seq
        self.jumps_left[i] = {}
        if self.mode[i] == CopterMode.AUTO and self.armed[i]:
            self._start_item(i, seq)
        else:
            self.mission_state[i] = MissionState.NOT_STARTED
        self._emit(i, Event.MISSION_CURRENT, seq)
        return OK

    def change_speed(self, i: int, speed_mps: float) -> CommandOutcome:
        if not math.isfinite(speed_mps) or speed_mps <= 0 or speed_mps > 50:
            return CommandOutcome(Result.DENIED, f"Speed {speed_mps} m/s outside 0..50")
        self.speed_xy_mps[i] = speed_mps
        return OK

    def goto(self, i: int, goal_m) -> CommandOutcome:
        if self.mode[i] != CopterMode.GUIDED or not self._flying(i):
            return CommandOutcome(Result.TEMPORARILY_REJECTED, "Goto refused: needs GUIDED mode and flying")
        goal = np.asarray(goal_m, dtype=float).copy()
        goal[2] = max(goal[2], 0.5)
        self._set_goal(i, goal, Motion.GOTO, Check.NONE)
        return OK

    def setpoint(self, i: int, target: Setpoint) -> bool:
        """A GUIDED setpoint (sitl.vehicle.guided); ignored, as ArduCopter does, outside GUIDED or on the
        ground. Returns whether it was taken."""
        if self.mode[i] != CopterMode.GUIDED or not self._flying(i):
            return False
        if target.pos_m is not None:
            self.goto(i, target.pos_m)
        elif target.is_velocity_control:
            self.velocity_mps[i] = target.vel_mps if target.vel_mps is not None else self.state.vel_mps[i]
            self.accel_mps2[i] = target.acc_mps2 if target.acc_mps2 is not None else 0.0
            self._set_goal(i, self._pos(i), Motion.VELOCITY, Check.NONE)
            self._timer(i, VELOCITY_TIMEOUT_S, Phase.VELOCITY)
        else:
            self._hold(i)  # every group ignored: ArduCopter stops
        self.yaw_target_rad[i] = math.nan if target.yaw_rad is None else target.yaw_rad
        self.yaw_rate_rps[i] = math.nan if target.yaw_rate_rps is None else target.yaw_rate_rps
        return True

    def condition_yaw(self, i: int, angle_deg: float, speed_dps: float, direction: float,
                      relative: bool) -> CommandOutcome:
        """CONDITION_YAW: turn to a heading (relative: by an angle, -1 counter-clockwise, 1 clockwise) at a
        rate (0: the vehicle's default)."""
        if not (math.isfinite(angle_deg) and 0.0 <= angle_deg <= 360.0 and math.isfinite(speed_dps)):
            return CommandOutcome(Result.DENIED, f"Yaw refused: angle {angle_deg} outside 0..360")
        heading = float(self.state.yaw_rad[i]) if self.state is not None else 0.0
        turn = math.radians(angle_deg)
        self.yaw_target_rad[i] = heading + (-turn if direction < 0 else turn) if relative else turn
        self.yaw_rate_rps[i] = math.radians(abs(speed_dps)) if speed_dps else math.nan
        self.roi_m[i] = math.nan
        return OK

    def set_roi(self, i: int, roi_m) -> CommandOutcome:
        """DO_SET_ROI_LOCATION / DO_SET_ROI: point the nose at a place (None: stop doing so)."""
        if roi_m is None:
            self.roi_m[i] = math.nan
            self.yaw_target_rad[i] = math.nan
        else:
            self.roi_m[i] = roi_m
        return OK

    def pause(self, i: int, pause: bool) -> CommandOutcome:
        """DO_PAUSE_CONTINUE in AUTO or GUIDED: stop where the vehicle is, then go on with what it was doing."""
        if self.mode[i] not in (CopterMode.AUTO, CopterMode.GUIDED) or not self._flying(i):
            return CommandOutcome(Result.DENIED, "Pause/continue: needs AUTO or GUIDED and flying")
        if pause:
            if self.paused[i] is None:
                left_s = self.until_t_s[i] - self.t_s if self.check[i] == Check.TIMER else math.inf
                self.paused[i] = (self.goal_m[i].copy(), int(self.motion[i]), int(self.check[i]),
                                  float(self.radius_m[i]), self.phase[i], left_s, int(self.mission_state[i]))
                self._set_goal(i, self._pos(i), Motion.GOTO, Check.NONE)
                if self.mode[i] == CopterMode.AUTO:
                    self.mission_state[i] = MissionState.PAUSED
                self._text(i, "Paused")
            return OK
        saved, self.paused[i] = self.paused[i], None
        if saved is None:
            return OK
        goal, motion, check, radius_m, phase, left_s, mission_state = saved
        self._set_goal(i, goal, Motion(motion), Check(check), radius_m, phase)
        if check == Check.TIMER:
            self.until_t_s[i] = self.t_s + left_s
        self.mission_state[i] = mission_state
        self._text(i, "Resumed")
        return OK

    def set_servo(self, i: int, channel: int, pwm: int) -> CommandOutcome:
        """DO_SET_SERVO: remembered (and acknowledged) as ArduCopter does; outputs 1-4 drive the motors."""
        if not 1 <= channel <= 32 or not 0 <= pwm <= 65535:
            return CommandOutcome(Result.DENIED, f"Servo {channel} PWM {pwm} out of range")
        if channel <= 4:
            return CommandOutcome(Result.FAILED, f"Servo {channel} is a motor output")
        self.servo_pwm[i][channel] = pwm
        return OK

    def set_home(self, i: int, home_m: np.ndarray | None) -> CommandOutcome:
        """DO_SET_HOME: here (None) or a given place. RTL, relative altitudes and HOME_POSITION follow home; the
        local frame's origin (ArduPilot's EKF origin) stays, and with it LOCAL_POSITION_NED."""
        if home_m is None:
            if not self.gps_ok[i]:
                return CommandOutcome(Result.FAILED, "Set home refused: no position")
            home_m = self._pos(i)
        home_m = np.asarray(home_m, dtype=float)
        if not np.isfinite(home_m).all() or np.hypot(*home_m[:2]) > HOME_FROM_ORIGIN_MAX_M:
            return CommandOutcome(Result.FAILED, "Set home refused: more than 50 km from the EKF origin")
        self.home_m[i] = home_m
        self.home_locked[i] = True
        self._emit(i, Event.HOME, None)
        return OK

    def reboot(self, i: int) -> CommandOutcome:
        """What a restart leaves: missions and parameters (stored), nothing in flight; disarmed only."""
        if self.armed[i]:
            return CommandOutcome(Result.FAILED, "Reboot refused: disarm first")
        self.mode[i] = CopterMode.STABILIZE
        self._set_goal(i, self._pos(i), Motion.IDLE, Check.NONE)
        self.failsafe[i] = False
        self.yaw_target_rad[i] = self.yaw_rate_rps[i] = math.nan
        self.roi_m[i] = math.nan
        self.home_locked[i] = False
        self.paused[i] = None
        self.speed_xy_mps[i] = self.params.get(i, "WPNAV_SPEED") / 100.0
        if len(self.mission(i)) > 1:
            self.current_seq[i] = 1
            self.mission_state[i] = MissionState.NOT_STARTED
        return OK

    def on_params_changed(self) -> None:
        """A new WPNAV_SPEED applies at once; a mission's DO_CHANGE_SPEED below it stays while in AUTO."""
        limits = self.params.column("WPNAV_SPEED") / 100.0
        in_auto = self.mode == CopterMode.AUTO
        self.speed_xy_mps = np.where(in_auto, np.minimum(self.speed_xy_mps, limits), limits)

