"""Autopilot parameters: definitions, per-vehicle values, validation and their physics arrays (pure).

Names follow ArduCopter where ArduCopter has the same meaning (and its units: cm, cm/s), so ground stations
show familiar names; NAC_* are this simulator's own (the research's controller gains), SIM_* inject faults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nac_onboard.errors import BadInput
from sitl.vehicle.physics import PhysicsParams


@dataclass(frozen=True)
class ParamDef:
    name: str
    default: float
    min: float
    max: float
    doc: str


PARAM_DEFS: tuple[ParamDef, ...] = (
    ParamDef("SYSID_THISMAV", 1, 1, 255, "MAVLink system id (read-only here: set by vehicle index)"),
    ParamDef("NAC_KP_XY", 0.15, 0.0, 10.0, "horizontal position gain k_x = k_y (1/s)"),
    ParamDef("NAC_KP_Z", 1.0, 0.0, 10.0, "vertical position gain k_z (1/s)"),
    ParamDef("NAC_VEL_TAU", 0.3, 0.01, 5.0, "velocity response time constant (s)"),
    ParamDef("WPNAV_SPEED", 500, 20, 2000, "horizontal speed limit (cm/s)"),
    ParamDef("WPNAV_SPEED_UP", 250, 10, 1000, "climb speed limit (cm/s)"),
    ParamDef("WPNAV_SPEED_DN", 150, 10, 500, "descent speed limit (cm/s)"),
    ParamDef("WPNAV_RADIUS", 200, 5, 1000, "waypoint acceptance radius (cm)"),
    ParamDef("LAND_SPEED", 50, 30, 200, "final descent speed (cm/s)"),
    ParamDef("RTL_ALT", 1500, 200, 8000, "return-to-launch altitude (cm)"),
    ParamDef("PILOT_TKOFF_ALT", 0, 0, 1000, "default takeoff altitude when none is given (cm)"),
    ParamDef("DISARM_DELAY", 2, 0, 127, "seconds on the ground after landing before auto-disarm"),
    ParamDef("BATT_CAPACITY", 5000, 100, 100000, "battery capacity (mAh)"),
    ParamDef("BATT_CELLS", 4, 1, 14, "battery cells in series"),
    ParamDef("BATT_HOVER_AMPS", 15, 0, 200, "current drawn in hover (A)"),
    ParamDef("BATT_LOW_PCT", 20, 0, 99, "state of charge that triggers the low-battery failsafe (%)"),
    ParamDef("BATT_FS_LOW_ACT", 2, 0, 2, "low-battery action: 0 none, 1 land, 2 RTL"),
    ParamDef("SIM_GPS_NOISE", 0, 0, 10, "GPS horizontal noise sigma (m); vertical is 1.5x"),
    ParamDef("SIM_GPS_DISABLE", 0, 0, 1, "fault: 1 = GPS lost (no fix, frozen position, vehicle lands)"),
    ParamDef("SIM_BATT_PCT", -1, -1, 100, "fault: set battery state of charge (%), -1 = no override"),
    ParamDef("SIM_LOSS_GCS", 0, 0, 100, "fault: packet loss on the ground link, both directions (%)"),
    ParamDef("SIM_LOSS_CC", 0, 0, 100, "fault: packet loss on the companion link, both directions (%)"),
    ParamDef("SIM_LINK_DOWN", 0, 0, 3, "fault: links down, bitmask 1 = ground, 2 = companion"),
    ParamDef("SIM_MIS_RETRY_MS", 250, 10, 5000, "mission upload: re-request an item after this long without it (ms)"),
    ParamDef("SIM_SPEEDUP", 1, 0.1, 1000, "simulation speed-up (read-only: set at start)"),
)
PARAMS_BY_NAME = {p.name: p for p in PARAM_DEFS}
READ_ONLY = frozenset({"SYSID_THISMAV", "SIM_SPEEDUP"})


class ParamError(BadInput):
    pass


class ParamTable:
    """Values of every parameter for every vehicle, as a (N, P) array in PARAM_DEFS order."""

    def __init__(self, n: int):
        self.values = np.tile(np.array([p.default for p in PARAM_DEFS], dtype=float), (n, 1))
        self.values[:, self.index("SYSID_THISMAV")] = np.arange(1, n + 1)

    @staticmethod
    def index(name: str) -> int:
        for i, p in enumerate(PARAM_DEFS):
            if p.name == name:
                return i
        raise ParamError(f"unknown parameter {name!r}")

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
        if not math.isfinite(value) or not definition.min <= value <= definition.max:
            raise ParamError(f"{name}={value} outside {definition.min}..{definition.max}")
        self.values[vehicle, self.index(name)] = value
        return value

    def physics(self) -> PhysicsParams:
        n = self.values.shape[0]
        base = PhysicsParams.defaults(n)
        return PhysicsParams(
            k_xy=self.column("NAC_KP_XY").copy(), k_z=self.column("NAC_KP_Z").copy(),
            speed_xy_max_mps=self.column("WPNAV_SPEED") / 100.0,
            speed_up_max_mps=self.column("WPNAV_SPEED_UP") / 100.0,
            speed_down_max_mps=self.column("WPNAV_SPEED_DN") / 100.0,
            land_speed_mps=self.column("LAND_SPEED") / 100.0,
            vel_tau_s=self.column("NAC_VEL_TAU").copy(),
            batt_capacity_mah=self.column("BATT_CAPACITY").copy(), batt_cells=self.column("BATT_CELLS").copy(),
            hover_current_a=self.column("BATT_HOVER_AMPS").copy(),
            current_per_mps_a=base.current_per_mps_a, idle_current_a=base.idle_current_a,
        )


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
