"""Autopilot parameters: definitions, per-vehicle values, validation and their physics arrays (pure).

Names follow ArduCopter where ArduCopter has the same meaning (and its units: cm, cm/s), so ground stations
show familiar names; NAC_* are this simulator's own (the research's controller gains), SIM_* inject faults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nac_onboard.errors import BadInput
from sitl.vehicle import energy
from sitl.vehicle.physics import PhysicsParams

INT8, INT16, INT32, REAL32 = "INT8", "INT16", "INT32", "REAL32"  # MAV_PARAM_TYPE names, ArduPilot's storage
INT_RANGES = {INT8: (-128, 127), INT16: (-32768, 32767), INT32: (-2**31, 2**31 - 1)}
NOT_SIMULATED = "stored and reported for ground stations; not simulated"


@dataclass(frozen=True)
class ParamDef:
    name: str
    default: float
    min: float
    max: float
    doc: str
    kind: str = REAL32  # the type ArduCopter stores it as (integer parameters read back as integers)


PARAM_DEFS: tuple[ParamDef, ...] = (
    ParamDef("SYSID_THISMAV", 1, 1, 255, "MAVLink system id (vehicle index + 1 at start; a new value is used from "
             "the next reboot, as ArduPilot's)", INT16),
    ParamDef("FRAME_CLASS", 1, 0, 15, f"1 = quad ({NOT_SIMULATED}: a point mass flies)", INT8),
    ParamDef("FRAME_TYPE", 1, 0, 18, f"1 = X ({NOT_SIMULATED})", INT8),
    ParamDef("ARMING_CHECK", 1, 0, 2**31 - 1, "pre-arm checks: 0 none, 1 all (GPS fix and battery here)", INT32),
    ParamDef("CIRCLE_RADIUS", 1000, 0, 200000, "CIRCLE mode's radius (cm); the centre is this far ahead of the "
             "vehicle when the mode starts"),
    ParamDef("CIRCLE_RATE", 20, -90, 90, "CIRCLE mode's and NAV_LOITER_TURNS' turn rate (deg/s, positive "
             "clockwise)"),
    ParamDef("SRTL_ACCURACY", 2, 0, 10, "SMART_RTL: a breadcrumb every this many metres; the way back keeps "
             "within it of the way out (m)"),
    ParamDef("SRTL_POINTS", 300, 0, 500, "SMART_RTL: breadcrumbs kept (beyond: every other one goes)", INT16),
    ParamDef("AUTO_OPTIONS", 0, 0, 2**31 - 1, f"AUTO's options: bit 0 (1) allows arming in AUTO (other bits "
             f"{NOT_SIMULATED})", INT32),
    ParamDef("NAC_NAV_LAW", 0, 0, 1, "how goals are flown: 0 ArduCopter's WPNav (trapezoid legs, WPNAV_ACCEL, LAND's "
             "two speeds), 1 the research's proportional law v = k (goal - x) (its scenarios set it)", INT8),
    ParamDef("NAC_KP_XY", 0.15, 0.0, 10.0, "horizontal position gain k_x = k_y (1/s)"),
    ParamDef("NAC_KP_Z", 1.0, 0.0, 10.0, "vertical position gain k_z (1/s)"),
    ParamDef("NAC_VEL_TAU", 0.3, 0.01, 5.0, "velocity response time constant (s)"),
    ParamDef("WPNAV_SPEED", 500, 20, 2000, "horizontal speed limit (cm/s)"),
    ParamDef("WPNAV_SPEED_UP", 250, 10, 1000, "climb speed limit (cm/s)"),
    ParamDef("WPNAV_SPEED_DN", 150, 10, 500, "descent speed limit (cm/s)"),
    ParamDef("WPNAV_RADIUS", 200, 5, 1000, "waypoint acceptance radius (cm)"),
    ParamDef("WPNAV_ACCEL", 250, 50, 500, "horizontal acceleration of ArduCopter's law (cm/s/s)"),
    ParamDef("WPNAV_ACCEL_Z", 100, 50, 500, "vertical acceleration of ArduCopter's law (cm/s/s)"),
    ParamDef("LOIT_SPEED", 1250, 20, 3500, "pilot modes: horizontal speed at full stick (cm/s)"),
    ParamDef("PILOT_SPEED_UP", 250, 50, 500, "pilot modes: climb at full throttle (cm/s)", INT16),
    ParamDef("PILOT_SPEED_DN", 150, 0, 500, "pilot modes: descent at zero throttle (cm/s)", INT16),
    ParamDef("WP_YAW_BEHAVIOR", 2, 0, 3, f"yaw in missions ({NOT_SIMULATED}: the nose follows the path)", INT8),
    ParamDef("LAND_SPEED", 50, 30, 200, "final descent speed (cm/s)", INT16),
    ParamDef("LAND_SPEED_HIGH", 0, 0, 500, "descent above LAND_ALT_LOW, 0 = WPNAV_SPEED_DN (cm/s)", INT16),
    ParamDef("LAND_ALT_LOW", 1000, 100, 10000, "below this LAND descends at LAND_SPEED (cm)", INT16),
    ParamDef("RTL_ALT", 1500, 200, 300000, "return-to-launch altitude (cm)", INT32),
    ParamDef("RTL_ALT_FINAL", 0, 0, 1000, f"RTL final altitude, 0 = land (cm; {NOT_SIMULATED})", INT16),
    ParamDef("RTL_CLIMB_MIN", 0, 0, 3000, f"RTL minimum climb (cm; {NOT_SIMULATED})", INT16),
    ParamDef("RTL_SPEED", 0, 0, 2000, f"RTL speed, 0 = WPNAV_SPEED (cm/s; {NOT_SIMULATED})", INT16),
    ParamDef("RTL_LOIT_TIME", 5000, 0, 60000, f"RTL loiter over home (ms; {NOT_SIMULATED})", INT32),
    ParamDef("PILOT_TKOFF_ALT", 0, 0, 1000, "default takeoff altitude when none is given (cm)"),
    ParamDef("DISARM_DELAY", 10, 0, 127, "seconds armed on the ground (not taking off, or landed in a mode "
             "that does not disarm on landing) before the vehicle disarms itself; 0 = never", INT8),
    ParamDef("FENCE_ENABLE", 0, 0, 1, "geofence on (also DO_FENCE_ENABLE)", INT8),
    ParamDef("FENCE_TYPE", 7, 0, 15, "fence kinds: 1 altitude ceiling, 2 circle about home, 4 uploaded zones", INT8),
    ParamDef("FENCE_ACTION", 1, 0, 7, "breach action: 0 report only, 2 land, 4 brake, others RTL", INT8),
    ParamDef("FENCE_ALT_MAX", 100, 10, 1000, "fence ceiling (m above home)"),
    ParamDef("FENCE_RADIUS", 300, 30, 10000, "circular fence about home (m)"),
    ParamDef("FENCE_MARGIN", 2, 1, 10, f"distance kept from the fence (m; {NOT_SIMULATED})"),
    ParamDef("RALLY_INCL_HOME", 1, 0, 1, "RTL may go home as well as to the nearest rally point", INT8),
    ParamDef("RALLY_LIMIT_KM", 0.3, 0, 100, "rally points farther than this are not used, 0 = no limit (km)"),
    ParamDef("FS_THR_ENABLE", 1, 0, 6, f"radio failsafe ({NOT_SIMULATED}: no radio)", INT8),
    ParamDef("FS_GCS_ENABLE", 0, 0, 7, f"ground-station failsafe ({NOT_SIMULATED})", INT8),
    ParamDef("FS_EKF_ACTION", 1, 1, 3, "EKF failsafe action (here: GPS lost lands)", INT8),
    ParamDef("BATT_CAPACITY", 5000, 100, 100000, "battery capacity (mAh)", INT32),
    ParamDef("BATT_CELLS", 4, 1, 14, "battery cells in series", INT8),
    ParamDef("NAC_FRAME", 0, 0, len(energy.FRAME_NAMES) - 1, "airframe whose propulsion power the battery feeds: "
             + ", ".join(f"{i} {name}" for i, name in enumerate(energy.FRAME_NAMES)) + " (sitl/vehicle/energy.py)",
             INT8),
    ParamDef("BATT_LOW_PCT", 20, 0, 99, "state of charge that triggers the low-battery failsafe (%)", INT8),
    ParamDef("BATT_LOW_VOLT", 10.5, 0, 100, "resting voltage (the voltage under load plus the internal resistance's "
             "drop) that triggers the low-battery failsafe after BATT_LOW_TIMER, 0 = off (V)"),
    ParamDef("BATT_LOW_TIMER", 10, 0, 120, "seconds the resting voltage must stay below BATT_LOW_VOLT (s)", INT8),
    ParamDef("BATT_FS_LOW_ACT", 2, 0, 2, "low-battery action: 0 none, 1 land, 2 RTL", INT8),
    ParamDef("SIM_GPS_NOISE", 0, 0, 10, "GPS horizontal noise sigma (m); vertical is 1.5x"),
    ParamDef("SIM_GPS_DISABLE", 0, 0, 1, "fault: 1 = GPS lost (no fix, frozen position, vehicle lands)", INT8),
    ParamDef("SIM_BATT_PCT", -1, -1, 100, "fault: set battery state of charge (%), -1 = no override"),
    ParamDef("SIM_LOSS_GCS", 0, 0, 100, "fault: packet loss on the ground link, both directions (%)"),
    ParamDef("SIM_LOSS_CC", 0, 0, 100, "fault: packet loss on the companion link, both directions (%)"),
    ParamDef("SIM_LINK_DOWN", 0, 0, 3, "fault: links down, bitmask 1 = ground, 2 = companion", INT8),
    ParamDef("SIM_MIS_RETRY_MS", 250, 10, 5000, "mission upload: re-request an item after this long without it (ms)",
             INT16),
    ParamDef("SIM_SPEEDUP", 1, 0.1, 1000, "simulation speed-up (read-only: set at start)"),
)
PARAMS_BY_NAME = {p.name: p for p in PARAM_DEFS}
PARAM_INDEX = {p.name: k for k, p in enumerate(PARAM_DEFS)}
READ_ONLY = frozenset({"SIM_SPEEDUP"})


class ParamError(BadInput):
    pass


class ParamTable:
    """Values of every parameter for every vehicle, as a (N, P) array in PARAM_DEFS order: the values the vehicle
    acts on. A ground station's value outside a parameter's range is kept as sent (`reported`) as ArduPilot keeps it,
    while the vehicle acts on the nearest value in range."""

    def __init__(self, n: int):
        self.values = np.tile(np.array([p.default for p in PARAM_DEFS], dtype=float), (n, 1))
        self.values[:, self.index("SYSID_THISMAV")] = np.arange(1, n + 1)
        self._kept_out_of_range: dict[tuple[int, int], float] = {}  # (vehicle, column) -> the value a GCS sent

    @staticmethod
    def index(name: str) -> int:
        try:
            return PARAM_INDEX[name]
        except KeyError:
            raise ParamError(f"unknown parameter {name!r}") from None

    def get(self, vehicle: int, name: str) -> float:
        return float(self.values[vehicle, self.index(name)])

    def column(self, name: str) -> np.ndarray:
        return self.values[:, self.index(name)]

    def set(self, vehicle: int, name: str, value: float, *, force: bool = False) -> float:
        """Set a value after range checks; raises ParamError with the reason for the operator."""
        definition = PARAMS_BY_NAME.get(name)
        if definition is None:
            raise ParamError(f"unknown parameter {name!r}")
        if name in READ_ONLY and not force:
            raise ParamError(f"{name} is read-only")
        value = stored_value(definition, value)
        if not math.isfinite(value) or not definition.min <= value <= definition.max:
            raise ParamError(f"{name}={value:g} outside {definition.min:g}..{definition.max:g}")
        self.values[vehicle, self.index(name)] = value
        self._kept_out_of_range.pop((vehicle, self.index(name)), None)
        return value

    def store(self, vehicle: int, name: str, value: float) -> str | None:
        """PARAM_SET as ArduPilot takes it: any finite value is kept (integer types rounded into their storage
        range) and read back as kept, so a ground station that compares the echo with what it sent (MAVSDK) sees
        its value; the vehicle acts on the nearest value in the parameter's range. Returns a sentence for the
        operator when those differ. Read-only and unknown names, and values that are not finite, raise ParamError."""
        definition = PARAMS_BY_NAME.get(name)
        if definition is None:
            raise ParamError(f"unknown parameter {name!r}")
        if name in READ_ONLY:
            raise ParamError(f"Param write denied ({name})")
        if not math.isfinite(value):
            raise ParamError(f"{name}={value} is not a number")
        kept = stored_value(definition, value)
        if definition.kind in INT_RANGES:
            low, high = INT_RANGES[definition.kind]
            kept = float(min(max(kept, low), high))
        acted_on = min(max(kept, definition.min), definition.max)
        self.set(vehicle, name, acted_on)
        if acted_on == kept:
            return None
        self._kept_out_of_range[(vehicle, self.index(name))] = kept
        return f"{name} {kept:g} outside {definition.min:g}..{definition.max:g}: using {acted_on:g}"

    def reported(self, vehicle: int, name: str) -> float:
        """The value a ground station reads: as it was sent, even outside the range the vehicle acts on."""
        return self._kept_out_of_range.get((vehicle, self.index(name)), self.get(vehicle, name))

    def physics(self, frames: list | None = None) -> PhysicsParams:
        """The physics' arrays; frames: a Frame per vehicle that overrides NAC_FRAME's (None: NAC_FRAME's)."""
        frames = frames or [None] * self.values.shape[0]
        return PhysicsParams(
            k_xy=self.column("NAC_KP_XY").copy(), k_z=self.column("NAC_KP_Z").copy(),
            speed_xy_max_mps=self.column("WPNAV_SPEED") / 100.0,
            speed_up_max_mps=self.column("WPNAV_SPEED_UP") / 100.0,
            speed_down_max_mps=self.column("WPNAV_SPEED_DN") / 100.0,
            land_speed_mps=self.column("LAND_SPEED") / 100.0,
            vel_tau_s=self.column("NAC_VEL_TAU").copy(),
            batt_capacity_mah=self.column("BATT_CAPACITY").copy(), batt_cells=self.column("BATT_CELLS").copy(),
            power=energy.PowerArrays.of([own or energy.FRAMES[energy.FRAME_NAMES[int(i)]]
                                         for own, i in zip(frames, self.column("NAC_FRAME"), strict=True)]),
            research_law=self.column("NAC_NAV_LAW") == 1,
            accel_xy_mps2=self.column("WPNAV_ACCEL") / 100.0, accel_z_mps2=self.column("WPNAV_ACCEL_Z") / 100.0,
            land_speed_high_mps=np.where(self.column("LAND_SPEED_HIGH") > 0, self.column("LAND_SPEED_HIGH"),
                                         self.column("WPNAV_SPEED_DN")) / 100.0,
            land_alt_low_m=self.column("LAND_ALT_LOW") / 100.0,
        )


def stored_value(definition: ParamDef, value: float) -> float:
    """What ArduPilot keeps of a value for this parameter: integer types hold the nearest integer."""
    if definition.kind == REAL32 or not math.isfinite(value):
        return float(value)
    return float(round(value))


def parse_param_file(text: str, source: str) -> dict[str, float]:
    """ArduPilot/MAVProxy parameter file: `NAME VALUE` or `NAME,VALUE` per line, `#` comments."""
    values: dict[str, float] = {}
    for line_no, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").replace("\t", " ").split()
        if len(parts) != 2:
            raise ParamError(f"{source}:{line_no}: expected 'NAME VALUE', got {raw.strip()!r}")
        name, value_text = parts
        if name not in PARAMS_BY_NAME:
            raise ParamError(f"{source}:{line_no}: unknown parameter {name!r}")
        try:
            value = float(value_text)
        except ValueError:
            raise ParamError(f"{source}:{line_no}: {name} value {value_text!r} is not a number") from None
        d = PARAMS_BY_NAME[name]
        if not math.isfinite(value) or not d.min <= value <= d.max:
            raise ParamError(f"{source}:{line_no}: {name}={value} outside {d.min}..{d.max}")
        values[name] = value
    return values
