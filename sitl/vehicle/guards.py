"""What the simulated autopilots watch after every step and act on by themselves (pure): the geofence, the
battery and GPS failsafes, and the auto-disarm of a vehicle left armed on the ground.

The fence is built from the vehicle's fence items when first needed (sitl.vehicle.fence decides a breach);
actions are mode changes through sitl.vehicle.modes, as ArduCopter's FENCE_ACTION and BATT_FS_LOW_ACT take.
"""

from __future__ import annotations

import math

import numpy as np

from missions.model import MissionType
from sitl.vehicle import energy
from sitl.vehicle import fence as fence_
from sitl.vehicle.flight_state import CopterMode, FlightState, Severity
from sitl.vehicle.modes import Modes
from sitl.vehicle.physics import Motion, VehicleState


class Guards:
    """Fence, failsafes and auto-disarm of N autopilots over their shared flight state."""

    def __init__(self, s: FlightState, modes: Modes):
        self.s = s
        self.modes = modes  # what a breach or a failsafe switches to

    def check(self, state: VehicleState, t_s: float) -> None:
        """After a step: disarm the idle, watch the fences, then the battery and the GPS of every flying vehicle."""
        s = self.s
        self._auto_disarm(state, t_s)
        self._check_fences(state)
        flying = s.armed & ~state.on_ground
        low_batt = flying & ~s.failsafe & ((state.soc * 100.0 < s.params.column("BATT_LOW_PCT"))
                                            | self._low_voltage_for_long(state, flying, t_s))
        no_gps = flying & ~s.gps_ok & (s.mode != CopterMode.LAND)
        for i in np.flatnonzero(low_batt | no_gps):
            self._failsafe(int(i), bool(no_gps[i]))

    def _low_voltage_for_long(self, state: VehicleState, flying: np.ndarray, t_s: float) -> np.ndarray:
        """ArduPilot's voltage failsafe: the resting voltage (the terminal voltage plus the internal resistance's
        drop, which ArduPilot estimates and the simulator knows) below BATT_LOW_VOLT for BATT_LOW_TIMER seconds."""
        s = self.s
        threshold_v = s.params.column("BATT_LOW_VOLT")
        resting_v = state.voltage_v + state.current_a * s.params.column("BATT_CELLS") * energy.CELL_RESISTANCE_OHM
        low = flying & (threshold_v > 0) & (resting_v < threshold_v)
        s.low_volt_since_t_s[~low] = math.inf
        s.low_volt_since_t_s[low & np.isinf(s.low_volt_since_t_s)] = t_s
        return low & (t_s - s.low_volt_since_t_s >= s.params.column("BATT_LOW_TIMER"))

    def _check_fences(self, state: VehicleState) -> None:
        """FENCE_ENABLE: a flying vehicle that leaves the fence says so and takes FENCE_ACTION (0 report only,
        2 land, 4 brake, otherwise RTL); coming back inside clears the breach."""
        s = self.s
        watched = s.armed & ~state.on_ground & (s.params.column("FENCE_ENABLE") > 0)
        for i in np.flatnonzero(watched | np.not_equal(s.fence_breach, None)):
            i = int(i)
            reason = fence_.breach(self.fence(i), state.pos_m[i], int(s.params.get(i, "FENCE_TYPE")),
                                   s.params.get(i, "FENCE_ALT_MAX"), s.params.get(i, "FENCE_RADIUS")) \
                if watched[i] else None
            if reason is None:
                if s.fence_breach[i] is not None:
                    s.fence_breach[i] = None
                    s.text(i, "Fence breach cleared")
                continue
            if s.fence_breach[i] is not None:
                continue
            s.fence_breach[i] = reason
            s.text(i, f"Fence breached: {reason}", Severity.CRITICAL)
            action = int(s.params.get(i, "FENCE_ACTION"))
            if action == 0 or s.mode[i] in (CopterMode.RTL, CopterMode.LAND):
                continue
            self.modes.set_mode(i, {2: CopterMode.LAND, 4: CopterMode.BRAKE}.get(action, CopterMode.RTL))

    def fence(self, i: int) -> fence_.Fence:
        """Vehicle i's fence, built from its fence items (rebuilt after a new fence list is installed)."""
        s = self.s
        if s.fences[i] is None:
            s.fences[i] = fence_.fence_from_items(s.mission(i, MissionType.FENCE), s.homes[i])
        return s.fences[i]

    def _auto_disarm(self, state: VehicleState, t_s: float) -> None:
        """ArduCopter's DISARM_DELAY: a vehicle armed on the ground that does not take off disarms itself."""
        s = self.s
        idle = s.armed & state.on_ground & (s.motion == Motion.IDLE)
        s.idle_since_t_s[~idle] = math.inf
        s.idle_since_t_s[idle & np.isinf(s.idle_since_t_s)] = t_s
        delay_s = s.params.column("DISARM_DELAY")
        for i in np.flatnonzero(idle & (delay_s > 0) & (t_s - s.idle_since_t_s >= delay_s)):
            s.disarm(int(i), f"Auto-disarmed: armed on the ground for {delay_s[i]:g} s")

    def _failsafe(self, i: int, gps: bool) -> None:
        """GPS lost: land. Low battery: BATT_FS_LOW_ACT (0 warn only, 1 land, 2 RTL)."""
        s = self.s
        s.failsafe[i] = True
        if gps:
            s.text(i, "EKF failsafe: GPS lost, landing", Severity.CRITICAL)
            self.modes.set_mode(i, CopterMode.LAND)
            return
        action = int(s.params.get(i, "BATT_FS_LOW_ACT"))
        s.text(i, "Battery failsafe: low battery", Severity.CRITICAL)
        if action == 2:
            self.modes.set_mode(i, CopterMode.RTL)
        elif action == 1:
            self.modes.set_mode(i, CopterMode.LAND)
