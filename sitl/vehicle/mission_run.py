"""Mission execution of the simulated autopilots (pure): installing a mission, sequencing its items (DO items,
jumps, navigation goals, loiter turns) and the return to launch a mission or the RTL mode flies.

Mission item 0 is home, as on ArduPilot: execution starts at seq 1. Completion of a navigation goal is checked
each step by sitl.vehicle.flight, which calls `item_reached` here.
"""

from __future__ import annotations

import math

import numpy as np

from missions import firmware
from missions.model import MavCmd, MissionItem, MissionType
from sitl.vehicle import fence as fence_
from sitl.vehicle import mission_items as items_
from sitl.vehicle.actions import Actions
from sitl.vehicle.flight_state import (
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
from sitl.vehicle.physics import Motion, VehicleState


class MissionRun:
    """Where each vehicle is in its mission and what its current item asks, over the shared flight state."""

    def __init__(self, s: FlightState, actions: Actions):
        self.s = s
        self.actions = actions  # what the mission's DO items do

    def replace_mission(self, i: int, mission_type: int, items: list[MissionItem]) -> None:
        """Install a complete, validated list (seq 0..n-1); only called once a transfer has succeeded."""
        s = self.s
        s.missions[i][MissionType(mission_type)] = items
        if mission_type == MissionType.FENCE:
            s.fences[i] = None
        if mission_type != MissionType.MISSION:
            return
        s.jumps_left[i] = {}
        if len(items) <= 1:
            s.current_seq[i] = 0
            s.mission_state[i] = MissionState.NO_MISSION
            if s.mode[i] == CopterMode.AUTO:
                s.hold(i)
        else:
            if not 1 <= s.current_seq[i] < len(items):
                s.current_seq[i] = 1
            running = s.mode[i] == CopterMode.AUTO and s.armed[i]
            s.mission_state[i] = MissionState.ACTIVE if running else MissionState.NOT_STARTED
            if running:
                self.start_item(i, int(s.current_seq[i]))
        s.emit(i, Event.MISSION_CURRENT, int(s.current_seq[i]))

    def set_current(self, i: int, seq: int) -> CommandOutcome:
        """DO_SET_MISSION_CURRENT / MISSION_SET_CURRENT: go on from item seq (0 means 1: item 0 is home)."""
        s = self.s
        items = s.mission(i)
        if not 0 <= seq < len(items):
            return CommandOutcome(Result.DENIED, f"Set current refused: no item {seq} (mission has {len(items)})")
        seq = max(seq, 1)
        s.current_seq[i] = seq
        s.jumps_left[i] = {}
        if s.mode[i] == CopterMode.AUTO and s.armed[i]:
            self.start_item(i, seq)
        else:
            s.mission_state[i] = MissionState.NOT_STARTED
        s.emit(i, Event.MISSION_CURRENT, seq)
        return OK

    def item_reached(self, i: int) -> None:
        """The current item is done: say so and start the next."""
        s = self.s
        seq = int(s.current_seq[i])
        s.emit(i, Event.ITEM_REACHED, seq)
        self.start_item(i, seq + 1)

    def start_item(self, i: int, seq: int) -> None:
        """Run the mission from item seq: DO items and jumps at once, up to the next navigation item."""
        s = self.s
        items = s.mission(i)
        for _ in range(4 * len(items) + 2):  # bounds DO_JUMP chains that never reach a nav item
            if seq >= len(items):
                self._mission_complete(i)
                return
            item = items[seq]
            if s.current_seq[i] != seq:
                s.current_seq[i] = seq
                s.emit(i, Event.MISSION_CURRENT, seq)
            s.mission_state[i] = MissionState.ACTIVE
            cmd = item.command
            if cmd in (MavCmd.DO_JUMP, firmware.DO_JUMP_TAG):
                seq = self._jump(i, seq, item)
                continue
            if cmd in firmware.DO_ACTED or cmd in firmware.DO_NO_EFFECT:
                self._do(i, item)
                s.emit(i, Event.ITEM_REACHED, seq)
                seq += 1
                continue
            self._start_nav_item(i, item)
            return
        s.text(i, "Mission: DO_JUMP loop without a navigation command, stopping", Severity.ERROR)
        self._mission_complete(i)

    def _jump(self, i: int, seq: int, item: MissionItem) -> int:
        """The item after a DO_JUMP (to a seq) or DO_JUMP_TAG (to the JUMP_TAG with that number), counting its
        repeats (-1: for ever)."""
        s = self.s
        items = s.mission(i)
        if item.command == MavCmd.DO_JUMP:
            target = int(item.p1)
        else:
            target = next((k for k, it in enumerate(items) if it.command == firmware.JUMP_TAG and it.p1 == item.p1), -1)
        left = s.jumps_left[i].setdefault(seq, int(item.p2))
        if left == 0 or not 1 <= target < len(items):
            return seq + 1
        if left > 0:
            s.jumps_left[i][seq] = left - 1
        return target

    def _do(self, i: int, item: MissionItem) -> None:
        """A DO or CONDITION item of a running mission (those with no effect here are passed over)."""
        s = self.s
        cmd = item.command
        if cmd == MavCmd.DO_CHANGE_SPEED:
            if item.p2 > 0:
                s.speed_xy_mps[i] = item.p2
        elif cmd == MavCmd.CONDITION_YAW:
            self.actions.condition_yaw(i, item.p1, item.p2, item.p3, item.p4 >= 0.5)
        elif cmd == firmware.DO_SET_ROI_NONE or (cmd == firmware.DO_SET_ROI and item.lat_deg == item.lon_deg == 0.0):
            self.actions.set_roi(i, None)
        elif cmd in (firmware.DO_SET_ROI, firmware.DO_SET_ROI_LOCATION):
            self.actions.set_roi(i, s.item_goal_m(i, item))
        elif cmd == firmware.DO_SET_SERVO:
            self.actions.set_servo(i, int(item.p1), int(item.p2))
        elif cmd == firmware.DO_FENCE_ENABLE:
            self.actions.enable_fence(i, item.p1)
        elif cmd == firmware.DO_SET_HOME:
            self.actions.set_home(i, None if item.p1 >= 0.5 else s.item_goal_m(i, item))

    def _start_nav_item(self, i: int, item: MissionItem) -> None:
        s = self.s
        cmd = item.command
        goal = s.item_goal_m(i, item)
        here = s.pos(i)
        if cmd in firmware.TAKEOFFS:
            s.set_goal(i, [here[0], here[1], max(goal[2], here[2])], Motion.GOTO, Check.ALTITUDE,
                       phase=Phase.MISSION)
        elif cmd in firmware.LANDINGS:
            s.set_goal(i, [goal[0], goal[1], 0.0], Motion.LAND, Check.LANDED, phase=Phase.LAND)
        elif cmd == MavCmd.NAV_RETURN_TO_LAUNCH:
            self.begin_rtl(i)
        elif cmd == firmware.NAV_DELAY:
            s.set_goal(i, here, Motion.GOTO if s.flying(i) else Motion.IDLE, Check.NONE)
            if item.p1 < 0:
                s.text(i, "NAV_DELAY until a time of day is not simulated: not waiting", Severity.WARNING)
            s.timer(i, max(0.0, item.p1) if math.isfinite(item.p1) else 0.0, Phase.MISSION)
        elif cmd == MavCmd.NAV_LOITER_TURNS:
            count, radius_m = items_.turns(item)
            outward = here[:2] - goal[:2]
            norm = float(np.hypot(*outward))
            edge = goal[:2] + (outward / norm if norm > 1e-6 else np.array([0.0, 1.0])) * abs(radius_m)
            s.set_goal(i, [edge[0], edge[1], goal[2]], Motion.GOTO, Check.REACH, s.wp_radius_m(i),
                       Phase.TURNS_ENTER)
        elif cmd == MavCmd.NAV_LOITER_UNLIM:
            s.set_goal(i, goal, Motion.GOTO, Check.NONE, phase=Phase.LOITER_UNLIM)
        else:
            radius = item.p2 if cmd == MavCmd.NAV_WAYPOINT and item.p2 > 0 else s.wp_radius_m(i)
            holds = cmd == MavCmd.NAV_LOITER_TIME or items_.holds_s(item) > 0
            s.set_goal(i, goal, Motion.GOTO, Check.REACH, radius, Phase.MISSION_HOLD if holds else Phase.MISSION)

    def start_circle(self, i: int) -> None:
        """NAV_LOITER_TURNS: on the circle's edge, start going round it."""
        s = self.s
        item = s.mission(i)[s.current_seq[i]]
        count, radius_m = items_.turns(item)
        center = s.item_goal_m(i, item)
        s.set_goal(i, s.pos(i), Motion.VELOCITY, Check.NONE, phase=Phase.TURNS)
        s.circling[i] = [center, radius_m, 2 * math.pi * count, items_.angle_about(s.pos(i), center)]
        if count == 0:
            s.circling.pop(i)
            self.item_reached(i)

    def circle(self, state: VehicleState) -> None:
        """Loiter turns: steer each circling vehicle round its circle, count the angle it has gone round."""
        s = self.s
        k_xy, k_z = s.params.column("NAC_KP_XY"), s.params.column("NAC_KP_Z")
        for i, circle in list(s.circling.items()):
            center, radius_m, left_rad, last = circle
            bearing = items_.angle_about(state.pos_m[i], center)
            turned = (bearing - last + math.pi) % (2 * math.pi) - math.pi
            circle[2] = left_rad - (turned if radius_m > 0 else -turned)
            circle[3] = bearing
            if circle[2] <= 0:
                del s.circling[i]
                self.item_reached(i)
                continue
            s.velocity_mps[i] = items_.circle_velocity_mps(state.pos_m[i], center, radius_m,
                                                           max(float(k_xy[i]), 0.5), float(k_z[i]),
                                                           s.params.get(i, "CIRCLE_RATE"))

    def _mission_complete(self, i: int) -> None:
        s = self.s
        s.mission_state[i] = MissionState.COMPLETE
        s.emit(i, Event.MISSION_CURRENT, int(s.current_seq[i]))
        s.text(i, "Mission complete")
        if s.phase[i] != Phase.DISARM_WAIT:
            s.hold(i)

    def begin_rtl(self, i: int) -> None:
        """Climb to RTL_ALT, fly to the nearest rally point (or home), land there."""
        s = self.s
        here = s.pos(i)
        rally = fence_.rally_target(s.mission(i, MissionType.RALLY), s.homes[i], s.home_m[i], here,
                                    s.params.get(i, "RALLY_INCL_HOME") > 0, s.params.get(i, "RALLY_LIMIT_KM"))
        s.rtl_target_m[i] = s.home_m[i] if rally is None else rally
        if rally is not None:
            s.text(i, f"RTL: to the rally point {np.hypot(*(rally[:2] - here[:2])):.0f} m away")
        rtl_alt = max(here[2], s.home_m[i, 2] + s.params.get(i, "RTL_ALT") / 100.0)
        s.set_goal(i, [here[0], here[1], rtl_alt], Motion.GOTO, Check.ALTITUDE, phase=Phase.RTL_CLIMB)
