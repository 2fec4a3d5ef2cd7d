"""The simulated world: every vehicle's state, parameters, flight logic and sensors on one simulated clock (pure).

`World.step(dt_s)` advances physics and flight logic for all vehicles at once and returns the flight events
(item reached, mode changed, text...) for the MAVLink layer to announce. Parameter changes go through
`set_param`, which applies their side effects (physics limits, GPS and battery faults) and tells the listeners
(the MAVLink layer's mission timeout, the server's link faults). No sockets and no wall clock: the server decides
when to step.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from missions.geo import Home, enu_to_lla, enu_to_lla_many, lla_to_ecef, lla_to_enu, offset_home
from sitl.vehicle.flight import Autopilots, CopterMode, Event
from sitl.vehicle.params import ParamTable
from sitl.vehicle.physics import BATTERY_PERIOD_S, VehicleState, drain, gps_noise_m, step

GROUND, COMPANION = "ground", "companion"  # a vehicle's two MAVLink links (TELEM1, TELEM2)
LINK_DOWN_BITS = {GROUND: 1, COMPANION: 2}  # SIM_LINK_DOWN bitmask


GEAR_HEIGHT_M = 0.1  # where a landed vehicle's antenna sits


@dataclass(frozen=True)
class GpsFix:
    """What every vehicle's GPS reports this step: position (ENU about its home, with noise) and geodetic."""

    pos_m: np.ndarray  # (N, 3)
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_m: np.ndarray  # AMSL


class World:
    def __init__(self, homes: list[Home], params: dict[str, float] | None = None, seed: int = 0,
                 speedup: float = 1.0, frames: tuple = ()):
        n = len(homes)
        if n < 1:
            raise ValueError("need at least one vehicle")
        self.n = n
        self.homes = list(homes)
        self._home_lat = np.array([h.lat_deg for h in homes])
        self._home_lon = np.array([h.lon_deg for h in homes])
        self._home_alt = np.array([h.alt_m for h in homes])
        self.params = ParamTable(n)
        self.params.values[:, self.params.index("SIM_SPEEDUP")] = speedup
        for name, value in (params or {}).items():
            for i in range(n):
                self.params.set(i, name, float(value))
        self.frames = list(frames) or [None] * n  # airframes given as files, else NAC_FRAME's (energy.py)
        self.physics = self.params.physics(self.frames)
        self.state = VehicleState.at_rest(n, self.physics)
        self.autopilots = Autopilots(self.homes, self.params)
        self.autopilots.state = self.state
        self.rng = np.random.default_rng(seed)
        self.t_s = 0.0
        self._since_drain_s = 0.0
        self.boot_t_s = np.zeros(n)  # when each autopilot (re)started, simulated seconds
        self._last_fix_m = self.state.pos_m.copy()
        self._home_now: dict[int, tuple[tuple, Home]] = {}  # vehicle -> (its home_m, home_of's answer)
        self.step_observers: list[Callable[[float, VehicleState], None]] = []  # (t_s, state) after every step
        self.param_listeners: list[Callable[[], None]] = []  # after every parameter change
        self._apply_params()

    @staticmethod
    def spaced_homes(first: Home, vehicles: int, spacing_m: float) -> list[Home]:
        """Vehicle i's home i * spacing_m east of the first."""
        return [offset_home(first, i * spacing_m, 0.0) for i in range(vehicles)]

    # ---- time -----------------------------------------------------------------------------------------------
    def step(self, dt_s: float) -> list[tuple[int, Event, object]]:
        self.state = step(self.state, self.autopilots.command(), self.physics, dt_s)
        self.t_s += dt_s
        self._since_drain_s += dt_s
        if self._since_drain_s >= BATTERY_PERIOD_S - 1e-9:
            self.state = drain(self.state, self.physics, self.autopilots.armed, self._since_drain_s)
            self._since_drain_s = 0.0
        self.autopilots.update(self.state, self.t_s)
        for observe in self.step_observers:
            observe(self.t_s, self.state)
        events, self.autopilots.events = self.autopilots.events, []
        return events

    # ---- parameters and faults ------------------------------------------------------------------------------
    def set_param(self, vehicle: int, name: str, value: float) -> None:
        """Set after range checks (ParamError names the reason) and apply the side effects."""
        self.params.set(vehicle, name, value)
        self._apply_params()

    def store_param(self, vehicle: int, name: str, value: float) -> str | None:
        """A ground station's PARAM_SET, kept as ArduPilot keeps it (ParamTable.store), then the side effects."""
        note = self.params.store(vehicle, name, value)
        self._apply_params()
        return note

    def _apply_params(self) -> None:
        p = self.params
        self.physics = p.physics(self.frames)
        self.autopilots.gps_ok = p.column("SIM_GPS_DISABLE") < 0.5
        self.autopilots.on_params_changed()
        batt = p.column("SIM_BATT_PCT")
        override = batt >= 0
        if override.any():
            soc = self.state.soc.copy()
            soc[override] = batt[override] / 100.0
            self.state = replace(self.state, soc=soc)
            p.values[override, p.index("SIM_BATT_PCT")] = -1  # applied once, like a battery swap
        for listener in self.param_listeners:
            listener()

    def link_down(self, vehicle: int, link: str) -> bool:
        return bool(int(self.params.get(vehicle, "SIM_LINK_DOWN")) & LINK_DOWN_BITS[link])

    def set_link_down(self, vehicle: int, link: str, down: bool) -> None:
        bits = int(self.params.get(vehicle, "SIM_LINK_DOWN"))
        bits = bits | LINK_DOWN_BITS[link] if down else bits & ~LINK_DOWN_BITS[link]
        self.set_param(vehicle, "SIM_LINK_DOWN", bits)

    def loss_pct(self, vehicle: int, link: str) -> float:
        return self.params.get(vehicle, "SIM_LOSS_GCS" if link == GROUND else "SIM_LOSS_CC")

    def set_loss_pct(self, vehicle: int, link: str, pct: float) -> None:
        self.set_param(vehicle, "SIM_LOSS_GCS" if link == GROUND else "SIM_LOSS_CC", pct)

    def any_link_fault(self) -> bool:
        p = self.params
        columns = [p.index("SIM_LINK_DOWN"), p.index("SIM_LOSS_GCS"), p.index("SIM_LOSS_CC")]
        return bool(p.values[:, columns].any())

    # ---- sensors and coordinates ----------------------------------------------------------------------------
    def gps_fix(self) -> GpsFix:
        """Positions as the GPS reports them: frozen at the last fix while the GPS is lost, plus SIM_GPS_NOISE."""
        fix = self.autopilots.gps_ok
        self._last_fix_m[fix] = self.state.pos_m[fix]
        sigma = self.params.column("SIM_GPS_NOISE")
        reported = self._last_fix_m
        if sigma.any():
            reported = reported + gps_noise_m(self.rng, self.n, 1.0, 1.5) * sigma[:, None]
        lat, lon, _ = enu_to_lla_many(reported, self._home_lat, self._home_lon, self._home_alt)
        return GpsFix(reported, lat, lon, self._home_alt + reported[:, 2])

    def global_to_enu(self, vehicle: int, lat: float, lon: float, alt: float, relative: bool = True) -> np.ndarray:
        home = self.homes[vehicle]
        enu = lla_to_enu(lat, lon, home.alt_m, home)
        enu[2] = alt + self.autopilots.home_m[vehicle, 2] if relative else alt - home.alt_m
        return enu

    def home_of(self, vehicle: int) -> Home:
        """Where vehicle's home is now (DO_SET_HOME and arming move it from the origin of its frame). Kept until
        the home moves: HOME_POSITION is streamed, and the geodesy on one point costs more than the message."""
        home_m = tuple(self.autopilots.home_m[vehicle].tolist())
        known = self._home_now.get(vehicle)
        if known is None or known[0] != home_m:
            lat, lon, alt = enu_to_lla(self.autopilots.home_m[vehicle], self.homes[vehicle])
            known = self._home_now[vehicle] = (home_m, Home(float(lat), float(lon), float(alt)))
        return known[1]

    def positions_ecef_m(self) -> np.ndarray:
        """Every vehicle's true position, earth-centred (N, 3): what the radio between them sees."""
        lat, lon, alt = enu_to_lla_many(self.state.pos_m, self._home_lat, self._home_lon, self._home_alt)
        return lla_to_ecef(lat, lon, alt)

    def heights_m(self) -> np.ndarray:
        """Height above the ground under each vehicle (flat ground at its home), at least a landing gear's."""
        return np.maximum(self.state.pos_m[:, 2], GEAR_HEIGHT_M)

    def truth(self, vehicle: int) -> dict:
        """True state of one vehicle (for tests and tools): ENU about its home, geodetic, mode, armed."""
        s, f = self.state, self.autopilots
        lat, lon, alt = enu_to_lla(s.pos_m[vehicle], self.homes[vehicle])
        return {
            "t_s": self.t_s, "pos_m": s.pos_m[vehicle].copy(), "vel_mps": s.vel_mps[vehicle].copy(),
            "lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt),
            "rel_alt_m": float(s.pos_m[vehicle, 2]), "on_ground": bool(s.on_ground[vehicle]),
            "armed": bool(f.armed[vehicle]), "mode": CopterMode(int(f.mode[vehicle])).name,
            "soc": float(s.soc[vehicle]), "mission_seq": int(f.current_seq[vehicle]),
            "mission_state": int(f.mission_state[vehicle]),
        }
