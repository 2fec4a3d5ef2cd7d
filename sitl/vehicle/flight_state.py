"""The simulated autopilots' shared flight state and its vocabulary (pure).

Every part of the flight logic (sitl.vehicle.flight and the parts it composes: mission_run, modes, actions,
guards, pilot_input) reads and writes the one `FlightState`: per-vehicle arrays (mode, armed, goal, check,
phase, mission position...) and the few moves every part makes on them (set a goal, hold, start a timer,
disarm, announce an event). Results are MAV_RESULT numbers, events are plain tuples the MAVLink layer turns
into messages.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum, IntEnum

import numpy as np

from missions.geo import Home, lla_to_enu
from missions.model import AMSL_FRAMES, MissionItem, MissionType
from sitl.vehicle import fence as fence_
from sitl.vehicle import pilot
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
    CIRCLE = 7
    LAND = 9
    POSHOLD = 16
    BRAKE = 17
    SMART_RTL = 21


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
    SMART_RTL = "smart_rtl"  # flying its trail back, breadcrumb by breadcrumb (sitl.vehicle.smart_rtl)


class Check(IntEnum):
    NONE = 0
    REACH = 1  # within radius_m of goal (3D)
    ALTITUDE = 2  # climbed to the goal's altitude
    LANDED = 3  # touched down
    TIMER = 4  # sim time reached until_t


PILOT_MODES = frozenset({CopterMode.LOITER, CopterMode.POSHOLD, CopterMode.ALT_HOLD})
#: ArduCopter's other modes: refused by name, as ArduCopter refuses a mode its build or hardware lacks (a point mass
#: has no attitude to fly by hand, nothing to follow or throw; docs/sitl.md)
NOT_FLOWN_MODES = {1: "ACRO", 11: "DRIFT", 13: "SPORT", 14: "FLIP", 15: "AUTOTUNE", 18: "THROW", 19: "AVOID_ADSB",
                   20: "GUIDED_NOGPS", 22: "FLOWHOLD", 23: "FOLLOW", 24: "ZIGZAG", 25: "SYSTEMID",
                   26: "AUTOROTATE", 27: "AUTO_RTL", 28: "TURTLE"}
HOLD_MODES = frozenset({CopterMode.STABILIZE, CopterMode.ALT_HOLD, CopterMode.LOITER, CopterMode.POSHOLD,
                        CopterMode.BRAKE, CopterMode.GUIDED})
HOME_FROM_ORIGIN_MAX_M = 50_000.0  # ArduPilot refuses a home farther than this from the EKF origin
FORCE_DISARM_MAGIC = 21196  # COMPONENT_ARM_DISARM param 2: disarm even in flight (ArduPilot)


@dataclass(frozen=True)
class CommandOutcome:
    result: Result
    text: str = ""


OK = CommandOutcome(Result.ACCEPTED)


class FlightState:
    """The per-vehicle arrays of N autopilots; positions are ENU metres about each vehicle's own home."""

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
        self.circling: dict[int, list] = {}  # NAV_LOITER_TURNS, CIRCLE: [centre, radius, left (rad), last bearing]
        self.rtl_target_m = np.zeros((n, 3))  # where RTL goes: home or the nearest rally point
        self.trail_m: list[list[np.ndarray]] = [[] for _ in range(n)]  # SMART_RTL's breadcrumbs since arming
        self.trail_last_m = np.full((n, 3), math.nan)
        self.srtl_route: dict[int, list[np.ndarray]] = {}  # SMART_RTL: the breadcrumbs still to fly back to
        self.home_m = np.zeros((n, 3))  # home about the frame's origin (DO_SET_HOME moves home, not the origin)
        self.home_locked = np.zeros(n, dtype=bool)  # set by DO_SET_HOME: arming no longer moves home
        self.fences: list[fence_.Fence | None] = [None] * n  # built from the fence list when first needed
        self.fence_breach = np.full(n, None, dtype=object)  # why each vehicle is outside its fence, or None
        self.rc_us = np.tile(pilot.idle_channels(), (n, 1))  # RC_CHANNELS_OVERRIDE, else the idle receiver
        self.rc_overridden = np.zeros((n, pilot.CHANNELS), dtype=bool)
        self.rc_until_t_s = np.full(n, -math.inf)
        self.piloted = np.zeros(n, dtype=bool)  # flying on the sticks in a pilot mode
        self.idle_since_t_s = np.full(n, math.inf)  # armed, on the ground and not taking off, since
        self.low_volt_since_t_s = np.full(n, math.inf)  # flying with the resting voltage below BATT_LOW_VOLT, since
        self.paused: list[tuple | None] = [None] * n  # DO_PAUSE_CONTINUE: what to resume
        self.servo_pwm: list[dict[int, int]] = [{} for _ in range(n)]  # DO_SET_SERVO outputs (not simulated)
        self.t_s = 0.0
        self.state: VehicleState | None = None

    # ---- what the physics flies -----------------------------------------------------------------------
    def command(self) -> Command:
        return Command(motion=self.motion, goal_m=self.goal_m, armed=self.armed, speed_xy_mps=self.speed_xy_mps,
                       velocity_mps=self.velocity_mps, yaw_target_rad=self.yaw_target_rad,
                       yaw_rate_rps=self.yaw_rate_rps)

    def alt_tolerance_m(self) -> np.ndarray:
        """How close below its goal's altitude a climb counts as done."""
        return np.clip(0.1 * self.goal_m[:, 2], 0.1, 0.5)

    # ---- what every part does to the state ------------------------------------------------------------
    def emit(self, i: int, kind: Event, value: object = None) -> None:
        self.events.append((i, kind, value))

    def text(self, i: int, text: str, severity: Severity = Severity.INFO) -> None:
        self.emit(i, Event.TEXT, (severity, text))

    def pos(self, i: int) -> np.ndarray:
        assert self.state is not None
        return self.state.pos_m[i].copy()

    def flying(self, i: int) -> bool:
        return bool(self.armed[i] and self.state is not None and not self.state.on_ground[i])

    def set_goal(self, i: int, goal_m, motion: Motion, check: Check, radius_m: float = 0.0, phase: Phase = Phase.NONE):
        """A new goal: where to fly and how (motion), what completes it (check) and what then happens (phase)."""
        self.circling.pop(i, None)
        self.goal_m[i] = goal_m
        self.motion[i] = motion
        self.check[i] = check
        self.radius_m[i] = radius_m
        self.phase[i] = phase

    def hold(self, i: int) -> None:
        """Stop: brake to a hover in the air, stay idle on the ground."""
        if self.flying(i):
            self.set_goal(i, self.stopping_point_m(i), Motion.GOTO, Check.NONE)
        else:
            self.set_goal(i, self.pos(i), Motion.IDLE, Check.NONE)

    def stopping_point_m(self, i: int) -> np.ndarray:
        """Where a stop ends: here under the research's law; ahead by v^2 / 2a under ArduCopter's, which brakes
        to that point rather than turning back to where the stop was asked."""
        here = self.pos(i)
        if self.params.get(i, "NAC_NAV_LAW") == 1 or self.state is None:
            return here
        velocity = self.state.vel_mps[i]
        accel_xy = self.params.get(i, "WPNAV_ACCEL") / 100.0
        accel_z = self.params.get(i, "WPNAV_ACCEL_Z") / 100.0
        here[:2] += velocity[:2] * float(np.hypot(*velocity[:2])) / (2.0 * accel_xy)
        here[2] = max(here[2] + velocity[2] * abs(velocity[2]) / (2.0 * accel_z), 0.5)
        return here

    def timer(self, i: int, seconds: float, phase: Phase) -> None:
        """Complete the current goal `seconds` from now (simulated time) instead of by reaching it."""
        self.check[i] = Check.TIMER
        self.until_t_s[i] = self.t_s + seconds
        self.phase[i] = phase

    # ---- missions on board ----------------------------------------------------------------------------
    def mission(self, i: int, mission_type: int = MissionType.MISSION) -> list[MissionItem]:
        return self.missions[i][MissionType(mission_type)]

    def wp_radius_m(self, i: int) -> float:
        return self.params.get(i, "WPNAV_RADIUS") / 100.0

    def item_goal_m(self, i: int, item: MissionItem) -> np.ndarray:
        """Where a mission item's place is, ENU (no position: here); its altitude by its frame, not below 0."""
        here = self.pos(i)
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

    def disarm(self, i: int, text: str) -> None:
        """Motors off, whatever the vehicle was doing; a running mission is paused where it was."""
        self.armed[i] = False
        self.idle_since_t_s[i] = math.inf
        self.set_goal(i, self.pos(i), Motion.IDLE, Check.NONE)
        if self.mode[i] == CopterMode.AUTO and self.mission_state[i] == MissionState.ACTIVE:
            self.mission_state[i] = MissionState.PAUSED
        self.text(i, text)
        self.emit(i, Event.ARMED, False)

