"""What flying costs: a multirotor's propulsion power and its LiPo pack under that load (pure: no I/O).

Propulsion power in level flight at airspeed V is the rotary-wing model of Zeng, Xu and Zhang ("Energy Minimization
for Wireless Communication With Rotary-Wing UAV", IEEE Trans. Wireless Commun. 18(4), 2019, eq. (12)):

    P(V) = P0 (1 + 3 V² / U_tip²) + Pi (sqrt(1 + V⁴ / (4 v0⁴)) - V² / (2 v0²))^½ + ½ d0 ρ s A V³

blade profile, induced and parasite power, with P0 = δ/8 ρ s A Ω³ R³, Pi = (1 + k) W^1.5 / sqrt(2 ρ A) and
v0 = sqrt(W / (2 ρ A)) (their eq. (13)-(14)). A multirotor is taken as its rotors' total disc area (momentum theory
does not care how the disc is split). Climbing adds the rate of potential energy W·v_z; descending is given no
credit (the rotors still carry the weight: an upper bound, our assumption). The battery delivers that shaft power
through the motors and ESCs (`drive_efficiency`) plus the avionics' draw. There is no wind: airspeed is ground speed.

The pack: cells in series, each an open-circuit voltage that follows its state of charge (`CELL_OPEN_CIRCUIT_V`) behind
an internal resistance, so the voltage sags under load and recovers at rest, as a real pack's does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

GRAVITY_MPS2 = 9.80665
AIR_DENSITY_KGPM3 = 1.225  # sea level, Zeng et al. Table I

# Open-circuit voltage of one LiPo cell at rest against its state of charge: the chart hobby LiPo vendors print
# (4.20 V full, 3.82 V at half, 3.27 V empty). An assumption, not a datasheet: the research's packs are not named.
CELL_OPEN_CIRCUIT_V = (
    (0.00, 3.27), (0.05, 3.61), (0.10, 3.69), (0.20, 3.73), (0.30, 3.77), (0.40, 3.79), (0.50, 3.82),
    (0.60, 3.87), (0.70, 3.92), (0.80, 3.97), (0.90, 4.10), (1.00, 4.20))
CELL_RESISTANCE_OHM = 0.010  # per cell: a used 5 Ah pack (new ones measure 3-6 mOhm); the value NAC used before
_SOC_POINTS = np.array([p[0] for p in CELL_OPEN_CIRCUIT_V])
_OCV_POINTS = np.array([p[1] for p in CELL_OPEN_CIRCUIT_V])


@dataclass(frozen=True)
class Frame:
    """One airframe class: what Zeng's model needs, each value with its source in FRAMES."""

    name: str
    mass_kg: float  # all up: frame, motors, batteries, companion
    rotors: int
    rotor_radius_m: float
    blade_solidity: float  # s = blades x chord / (pi R)
    tip_speed_mps: float  # U_tip = Omega R in hover
    profile_drag_coefficient: float  # delta
    induced_correction: float  # k: induced power over momentum theory's
    drag_area_m2: float  # fuselage equivalent flat-plate area S_FP = d0 s A
    drive_efficiency: float  # shaft power over battery power (motors and ESCs)
    avionics_w: float  # autopilot, GPS and telemetry radio, armed or not
    source: str

    def __post_init__(self) -> None:
        for field in fields(self):
            value = getattr(self, field.name)
            if field.name in ("name", "source"):
                continue
            low, high = RANGES[field.name]
            if not (isinstance(value, (int, float)) and math.isfinite(value) and low <= value <= high):
                raise ValueError(f"{field.name} = {value!r}: expected {low:g}..{high:g}")

    @property
    def weight_n(self) -> float:
        return self.mass_kg * GRAVITY_MPS2

    @property
    def disc_area_m2(self) -> float:
        return self.rotors * math.pi * self.rotor_radius_m ** 2

    @property
    def profile_power_w(self) -> float:
        """P0: blade profile power in hover."""
        return (self.profile_drag_coefficient / 8 * AIR_DENSITY_KGPM3 * self.blade_solidity * self.disc_area_m2
                * self.tip_speed_mps ** 3)

    @property
    def induced_power_w(self) -> float:
        """Pi: induced power in hover."""
        return (1 + self.induced_correction) * self.weight_n ** 1.5 / math.sqrt(
            2 * AIR_DENSITY_KGPM3 * self.disc_area_m2)

    @property
    def hover_induced_velocity_mps(self) -> float:
        """v0: the mean rotor-induced velocity in hover."""
        return math.sqrt(self.weight_n / (2 * AIR_DENSITY_KGPM3 * self.disc_area_m2))

    @property
    def blade_per_speed2(self) -> float:
        """3 / U_tip²: the blade profile power grows by P0 times this per V²."""
        return 3.0 / self.tip_speed_mps ** 2

    @property
    def induced_per_speed4(self) -> float:
        """1 / (4 v0⁴)"""
        return 0.25 / self.hover_induced_velocity_mps ** 4

    @property
    def induced_per_speed2(self) -> float:
        """1 / (2 v0²)"""
        return 0.5 / self.hover_induced_velocity_mps ** 2

    @property
    def parasite_w_per_speed3(self) -> float:
        """½ d0 rho s A = ½ rho S_FP: parasite power is this times V³."""
        return 0.5 * AIR_DENSITY_KGPM3 * self.drag_area_m2


RANGES = {  # physical ranges: a frame outside them is refused, naming the field
    "mass_kg": (0.05, 100.0), "rotors": (1, 16), "rotor_radius_m": (0.01, 5.0), "blade_solidity": (0.001, 1.0),
    "tip_speed_mps": (1.0, 340.0), "profile_drag_coefficient": (0.0, 0.1), "induced_correction": (0.0, 1.0),
    "drag_area_m2": (0.0, 5.0), "drive_efficiency": (0.05, 1.0), "avionics_w": (0.0, 1000.0),
}

_ZENG = "Zeng, Xu, Zhang, IEEE TWC 2019, Table I"
# The other frames: delta and k are Zeng's; the hover tip speed comes from Zeng's blade loading C_T/s = 0.045
# (W / (rho A U_tip^2 s) of Table I), held the same: U_tip = sqrt(W / (rho A s 0.045)).
_BLADE_LOADING = 20.0 / (AIR_DENSITY_KGPM3 * 0.503 * 120.0 ** 2 * 0.05)


def _tip_speed_mps(mass_kg: float, rotors: int, radius_m: float, solidity: float) -> float:
    area_m2 = rotors * math.pi * radius_m ** 2
    return math.sqrt(mass_kg * GRAVITY_MPS2 / (AIR_DENSITY_KGPM3 * area_m2 * solidity * _BLADE_LOADING))


def _frame(name: str, mass_kg: float, rotors: int, radius_m: float, chord_m: float, drag_area_m2: float,
           source: str) -> Frame:
    solidity = 2 * chord_m / (math.pi * radius_m)  # two-bladed propellers
    return Frame(name, mass_kg, rotors, radius_m, solidity, _tip_speed_mps(mass_kg, rotors, radius_m, solidity),
                 0.012, 0.1, drag_area_m2, DRIVE_EFFICIENCY, AVIONICS_W, source)


DRIVE_EFFICIENCY = 0.75  # assumption: brushless motor ~85 % x ESC ~90 % at hover load, typical catalogue values
AVIONICS_W = 4.5  # assumption: Pixhawk-class autopilot, GPS and telemetry radio, 0.3 A at 14.8 V (NAC's old value)

FRAMES: dict[str, Frame] = {
    # The paper's example rotorcraft exactly (W = 20 N, R 0.4 m, Omega 300 rad/s, 4 blades, s 0.05, d0 0.6).
    "zeng-2019": Frame("zeng-2019", 20.0 / GRAVITY_MPS2, 1, 0.4, 0.05, 120.0, 0.012, 0.1, 0.6 * 0.05 * 0.503,
                       DRIVE_EFFICIENCY, AVIONICS_W, _ZENG),
    # The research's Tarot 650 class: quad, 650 mm wheelbase, 15 x 5.5 in two-bladed props (R 0.19 m, mean chord
    # ~3 cm); 2.9 kg all up with a 4S 5.2 Ah flight pack, a second pack, Jetson and router (our estimate from the
    # frame's 0.6 kg and typical parts); S_FP 0.02 m² (an estimate for a 0.3 m body with payload).
    "tarot-650": _frame("tarot-650", 2.9, 4, 0.1905, 0.030, 0.020,
                        "Tarot 650 Sport frame class; masses and drag estimated (energy.py)"),
    # DJI Flame Wheel F550: hexa, 550 mm, 10 x 4.5 in props (DJI's spec; R 0.127 m, mean chord ~2 cm), takeoff
    # weight 1.2-2.4 kg by DJI's spec: 2.2 kg with companion and two packs; S_FP 0.015 m² (estimate).
    "dji-f550": _frame("dji-f550", 2.2, 6, 0.127, 0.020, 0.015,
                       "DJI F550 spec (frame, props, takeoff weight); drag estimated (energy.py)"),
}
FRAME_NAMES = tuple(FRAMES)  # NAC_FRAME's values index this
FRAME_FIELDS = tuple(f.name for f in fields(Frame))


def frame_from_table(table: dict) -> Frame:
    """A [frame] table of a frame file as a Frame: every field given, numbers in RANGES, a name and a source;
    ValueError naming the field and what was expected."""
    if not isinstance(table, dict):
        raise ValueError("expected a [frame] table")
    unknown = sorted(set(table) - set(FRAME_FIELDS))
    if unknown:
        raise ValueError(f"unknown field {unknown[0]!r} (fields: {', '.join(FRAME_FIELDS)})")
    missing = [name for name in FRAME_FIELDS if name not in table]
    if missing:
        raise ValueError(f"{missing[0]}: missing (every field is needed: {', '.join(FRAME_FIELDS)})")
    for name in ("name", "source"):
        if not isinstance(table[name], str) or not table[name].strip():
            raise ValueError(f"{name}: expected a non-empty string, got {table[name]!r:.60}")
    for name, value in table.items():
        if name not in ("name", "source") and (isinstance(value, bool) or not isinstance(value, (int, float))):
            raise ValueError(f"{name} = {value!r:.60}: expected a number in {RANGES[name][0]:g}..{RANGES[name][1]:g}")
    if not float(table["rotors"]).is_integer():
        raise ValueError(f"rotors = {table['rotors']!r}: expected a whole number")
    return Frame(**{**table, "rotors": int(table["rotors"])})


def level_power_w(frame, speed_mps):
    """Zeng's propulsion power at horizontal airspeed V (W); `frame` may hold one frame's numbers or arrays."""
    v2 = np.square(speed_mps)
    blade = frame.profile_power_w * (1 + frame.blade_per_speed2 * v2)
    induced = frame.induced_power_w * np.sqrt(np.sqrt(1 + np.square(v2) * frame.induced_per_speed4)
                                              - v2 * frame.induced_per_speed2)
    return blade + induced + frame.parasite_w_per_speed3 * v2 * np.abs(speed_mps)


def shaft_power_w(frame, speed_xy_mps, climb_mps):
    """Level power plus W v_z while climbing (no credit for descent)."""
    return level_power_w(frame, speed_xy_mps) + frame.weight_n * np.maximum(climb_mps, 0.0)


def minimum_power_speed_mps(frame, top_mps: float = 40.0) -> float:
    """The speed of least level power (endurance speed), to 1 mm/s."""
    speeds = np.arange(0.0, top_mps, 0.001)
    return float(speeds[np.argmin(level_power_w(frame, speeds))])


@dataclass(frozen=True)
class PowerArrays:
    """Zeng's numbers for N vehicles as arrays, the way the vectorised physics steps them."""

    profile_power_w: np.ndarray
    blade_per_speed2: np.ndarray
    induced_power_w: np.ndarray
    induced_per_speed4: np.ndarray
    induced_per_speed2: np.ndarray
    parasite_w_per_speed3: np.ndarray
    weight_n: np.ndarray
    drive_efficiency: np.ndarray
    avionics_w: np.ndarray

    @staticmethod
    def of(frames: list[Frame]) -> PowerArrays:
        return PowerArrays(*(np.array([getattr(f, field.name) for f in frames], dtype=float)
                             for field in fields(PowerArrays)))


def open_circuit_v(soc, cells):
    """The pack's voltage at rest at state of charge soc (0..1; interp holds the ends beyond)."""
    return cells * np.interp(soc, _SOC_POINTS, _OCV_POINTS)


def pack_current_a(power_w, open_v, cells):
    """Current drawn from a pack of open-circuit voltage open_v to deliver power_w at its terminals: the smaller
    root of R I² - E I + P = 0. Past the most the pack can give (E² / 4R) it gives that most: a brown-out."""
    resistance = cells * CELL_RESISTANCE_OHM
    discriminant = np.maximum(np.square(open_v) - 4 * resistance * power_w, 0.0)
    return (open_v - np.sqrt(discriminant)) / (2 * resistance)


def terminal_v(open_v, current_a, cells):
    return open_v - current_a * cells * CELL_RESISTANCE_OHM


# ---- the companion's side: its computer and Wi-Fi router on a second pack ----------------------------------------
@dataclass(frozen=True)
class CompanionPower:
    """A companion computer: its draw idle and with the job's rank busy (W)."""

    name: str
    idle_w: float
    busy_w: float
    source: str


@dataclass(frozen=True)
class RadioPower:
    """A Wi-Fi radio: its draw idle, and while transmitting or receiving at its PHY rate (W)."""

    name: str
    idle_w: float
    tx_w: float
    rx_w: float
    phy_rate_bps: float  # air time of a byte when its link's rate is not known: 8 / this
    source: str


_BUDGET_NOTE = "busy: the module's power-mode budget (NVIDIA data sheet); idle: a third of it (assumed, not measured)"
COMPANIONS: dict[str, CompanionPower] = {
    # named as the device profiles are (nac_onboard/compute/devices/): one name per companion
    "jetson-tx2": CompanionPower("jetson-tx2", 5.0, 15.0, "Jetson TX2 Max-P 15 W; " + _BUDGET_NOTE),
    "jetson-xavier-nx": CompanionPower("jetson-xavier-nx", 6.7, 20.0, "Jetson Xavier NX 20 W mode; " + _BUDGET_NOTE),
    "jetson-orin-nano": CompanionPower("jetson-orin-nano", 5.0, 15.0, "Jetson Orin Nano 15 W mode; " + _BUDGET_NOTE),
    "jetson-orin-nx": CompanionPower("jetson-orin-nx", 8.3, 25.0, "Jetson Orin NX 25 W mode; " + _BUDGET_NOTE),
}
COMPANION_ALIASES = {"xavier-nx": "jetson-xavier-nx", "orin-nano": "jetson-orin-nano", "orin-nx": "jetson-orin-nx"}
RADIOS: dict[str, RadioPower] = {
    # A small 802.11n travel router: 2 W idle (assumed); transmit and receive add what Halperin et al. measured
    # for an 802.11n NIC over idle (HotPower 2010: about 1.3-2 W sending, 0.1-0.3 W receiving), at 65 Mbit/s
    # (MCS 7, one stream, 20 MHz).
    "wifi-router": RadioPower("wifi-router", 2.0, 3.7, 2.2, 65e6, "Halperin et al., HotPower 2010; idle assumed"),
}
DC_DC_EFFICIENCY = 0.9  # assumption: the 5 V / 19 V converters between the companion pack and its loads


def companion_power_w(profile: CompanionPower, busy_share: float) -> float:
    """The computer's draw with its rank busy busy_share (0..1) of the time."""
    return profile.idle_w + (profile.busy_w - profile.idle_w) * min(max(busy_share, 0.0), 1.0)


def radio_power_w(radio: RadioPower, tx_share: float, rx_share: float) -> float:
    """The radio's draw, transmitting tx_share and receiving rx_share of the time (their sum at most 1)."""
    tx = min(max(tx_share, 0.0), 1.0)
    rx = min(max(rx_share, 0.0), 1.0 - tx)
    return radio.idle_w + (radio.tx_w - radio.idle_w) * tx + (radio.rx_w - radio.idle_w) * rx


CELL_NOMINAL_V = 3.7  # a LiPo cell's nominal voltage, as packs are rated (Wh = cells x 3.7 V x Ah)


def rated_wh(cells: int, capacity_mah: float) -> float:
    return cells * CELL_NOMINAL_V * capacity_mah / 1000.0


@dataclass
class Pack:
    """A LiPo pack drained step by step (the companion's: the flight pack is stepped with the physics)."""

    cells: int
    capacity_mah: float
    soc: float = 1.0
    delivered_wh: float = 0.0

    def drain(self, power_w: float, dt_s: float) -> tuple[float, float]:
        """Deliver power_w for dt_s: (current A, terminal voltage V). An empty pack delivers nothing."""
        if self.soc <= 0.0:
            return 0.0, 0.0
        open_v = float(open_circuit_v(self.soc, self.cells))
        current_a = float(pack_current_a(power_w, open_v, self.cells))
        volts = float(terminal_v(open_v, current_a, self.cells))
        self.soc = max(self.soc - current_a * dt_s / 3.6 / self.capacity_mah, 0.0)
        self.delivered_wh += volts * current_a * dt_s / 3600.0
        return current_a, volts


def endurance_s(power_w: float, cells: int, capacity_mah: float, down_to_soc: float = 0.0,
                dt_s: float = 1.0) -> float:
    """Seconds a full pack delivers power_w until its state of charge reaches down_to_soc, drained dt_s at a time
    (the current for that power at the present voltage, as the simulator steps its packs)."""
    pack, t_s = Pack(cells, capacity_mah), 0.0
    while pack.soc > down_to_soc:
        pack.drain(power_w, dt_s)
        t_s += dt_s
    return t_s


def hover_endurance_s(frame: Frame, cells: int, capacity_mah: float, down_to_soc: float = 0.0,
                      dt_s: float = 1.0) -> float:
    """Seconds a full pack hovers `frame` until its state of charge reaches down_to_soc."""
    hover_w = float(level_power_w(frame, 0.0)) / frame.drive_efficiency + frame.avionics_w
    return endurance_s(hover_w, cells, capacity_mah, down_to_soc, dt_s)
