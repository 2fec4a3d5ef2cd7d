"""The pilot's input to the simulated autopilots (pure): RC_CHANNELS_OVERRIDE kept per vehicle and, in the
pilot modes (LOITER, POSHOLD, ALT_HOLD), flown as velocity and yaw-rate commands (sticks as sitl.vehicle.pilot
reads them); an override that times out is released and the copter holds where it is.
"""

from __future__ import annotations

import math

import numpy as np

from sitl.vehicle import pilot
from sitl.vehicle.flight_state import PILOT_MODES, Check, FlightState, Phase, Severity
from sitl.vehicle.physics import Motion, VehicleState


class PilotInput:
    """RC overrides and stick flying of N autopilots over their shared flight state."""

    def __init__(self, s: FlightState):
        self.s = s

    def rc_override(self, i: int, values: list[int]) -> None:
        """RC_CHANNELS_OVERRIDE: the channels it sets hold for RC_OVERRIDE_TIME."""
        s = self.s
        pilot.apply_override(s.rc_us[i], s.rc_overridden[i], values)
        s.rc_until_t_s[i] = s.t_s + pilot.OVERRIDE_TIMEOUT_S

    def fly_sticks(self, state: VehicleState) -> None:
        """Pilot modes follow the sticks as velocity and yaw-rate commands; an override that times out is
        released and the copter holds where it is."""
        s = self.s
        for i in np.flatnonzero(s.rc_overridden.any(axis=1)):
            i = int(i)
            if s.t_s >= s.rc_until_t_s[i]:
                s.rc_us[i], s.rc_overridden[i] = pilot.idle_channels(), False
                if s.piloted[i]:
                    s.text(i, "RC override timed out: holding", Severity.WARNING)
                    s.piloted[i] = False
                    s.hold(i)
                continue
            if not (s.armed[i] and s.mode[i] in PILOT_MODES):
                continue
            velocity, yaw_rate = pilot.stick_command(
                s.rc_us[i], bool(s.rc_overridden[i, 2]), float(state.yaw_rad[i]),
                s.params.get(i, "LOIT_SPEED") / 100.0, s.params.get(i, "PILOT_SPEED_UP") / 100.0,
                s.params.get(i, "PILOT_SPEED_DN") / 100.0)
            grounded = bool(state.on_ground[i]) and velocity[2] <= 0
            s.circling.pop(i, None)
            s.goal_m[i], s.check[i], s.phase[i] = state.pos_m[i], Check.NONE, Phase.NONE
            s.motion[i] = Motion.IDLE if grounded else Motion.VELOCITY
            s.velocity_mps[i], s.accel_mps2[i] = velocity, 0.0
            if yaw_rate:
                s.yaw_target_rad[i], s.yaw_rate_rps[i] = math.nan, yaw_rate
            elif math.isnan(s.yaw_target_rad[i]):  # the nose stays where the pilot left it
                s.yaw_target_rad[i], s.yaw_rate_rps[i] = float(state.yaw_rad[i]), math.nan
            s.piloted[i] = not grounded
