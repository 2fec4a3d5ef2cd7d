"""Channel models: what a radio between two vehicles is, as data (presets; TOML files are read and written by
nac_onboard.radio.files), and its median behaviour (no shadowing, no fading) at a distance.
nac_onboard.radio.air_link holds the formulas and the stepping of the time-varying parts (DESIGN.md 6).

Path-loss models:
  free-space        20 log10(d_m) + 20 log10(f_Hz) - 147.55
  log-distance      PL(d0) + 10 n log10(d / d0)   (PL(d0) defaults to free space at d0)
  dual-slope        n up to breakpoint_m, exponent_far beyond it
  two-ray           direct and ground-reflected rays summed in phase, with both antennas' live heights
  hata-urban        Okumura-Hata, small or medium city (the research's); hata-large-city, hata-suburban,
  hata-rural        hata-rural (open area). Hata is fitted for 150-1500 MHz, h_b 30-200 m, h_m 1-10 m,
                    d 1-20 km: between UAVs metres apart it is an extrapolation, which `validity` says.
Rate models: `shannon` (the research's: W log2(1 + S/N0)) or `802.11n` (an MCS table with rate adaptation and
packet errors). Below min_rate_bps a link is out of range: nothing gets through.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from nac_onboard.errors import BadInput
from nac_onboard.radio import air_link
from nac_onboard.radio.medium import DEFAULT_RETRY_LIMIT, MAX_RETRY_LIMIT

PATH_LOSS_MODELS = ("free-space", "log-distance", "dual-slope", "two-ray", "hata-urban", "hata-large-city",
                    "hata-suburban", "hata-rural")
RATE_MODELS = ("shannon", "802.11n")
MAC_MODELS = ("efficiency", "802.11")


class ChannelError(BadInput):
    pass


@dataclass(frozen=True)
class ChannelModel:
    name: str
    path_loss: str
    freq_mhz: float
    bandwidth_hz: float
    tx_power_dbm: float
    noise_w: float
    # path loss
    exponent: float = 2.0  # log-distance and dual-slope n (up to the breakpoint)
    ref_distance_m: float = 1.0  # d0
    ref_loss_db: float | None = None  # PL(d0); None = free space at d0
    breakpoint_m: float = 100.0  # dual-slope
    exponent_far: float = 4.0  # dual-slope n beyond the breakpoint
    antenna_height_m: float = 3.0  # two-ray, when the live heights are unknown (the research flew at 3.04 m)
    ground_permittivity: float = 15.0  # two-ray: relative permittivity of the ground (average soil)
    polarization: str = "vertical"  # two-ray: antennas' polarization (vertical | horizontal)
    base_height_m: float = 30.0  # Hata h_b
    mobile_height_m: float = 1.5  # Hata h_m
    # shadowing and fading (0 / None = none: the research's deterministic link)
    shadowing_sigma_db: float = 0.0
    shadowing_decorrelation_m: float = 10.0
    rician_k_db: float | None = None  # None or inf: no fading
    hover_speed_mps: float = 0.0  # how much a hovering vehicle still moves: static links fade slowly
    # rate
    rate_model: str = "shannon"
    channel_width_mhz: int = 20  # 802.11n: 20 or 40
    short_guard_interval: bool = False  # 802.11n: 400 ns instead of 800 ns
    mcs_offset_db: float = 0.0  # shifts every MCS threshold (negative: a better receiver than the standard's)
    per_slope_db: float = 1.0  # width of the frame-error waterfall at each threshold
    rate_adaptation_s: float = 0.0  # how far the rate choice lags the channel (0 = it follows at once)
    retry_limit: int = DEFAULT_RETRY_LIMIT  # MAC retransmissions before a packet is lost to IP (802.11's default)
    mac_efficiency: float = 1.0  # goodput / PHY rate (headers, contention, acknowledgements, TCP)
    # "efficiency": a transfer's rate is the PHY rate x mac_efficiency; "802.11": the frame-level medium's own costs
    # (nac_onboard.radio.medium: access, preamble, acknowledgement per aggregate), what a run on the frame-level air
    # ([network] air = "medium") writes into its radio, so the sleep network charges what the delay line does
    mac: str = "efficiency"
    background_airtime: float = 0.0  # the share of airtime other networks use
    min_rate_bps: float = 0.0
    max_rate_bps: float | None = None  # a radio's top rate (Shannon has none)
    # A per-transfer software cost, as bits at the link's rate (0 in every preset): kept for experiments that
    # model a measured stack cost; the radio itself is all above.
    overhead_bits: float = 0.0
    seed: int = 0
    # A replay table (nac_onboard.radio.replay, JSON): its recorded pairs' throughput replaces the model's rate
    # in the sleep emulation (the runner writes it for `--links replay:RUN`); "" = the model everywhere.
    replay_file: str = ""
    notes: str = ""
    sources: str = ""

    def __post_init__(self):
        def fail(text: str):
            raise ChannelError(f"channel {self.name!r}: {text}")

        if self.path_loss not in PATH_LOSS_MODELS:
            fail(f"path_loss must be one of {', '.join(PATH_LOSS_MODELS)}, got {self.path_loss!r}")
        if self.rate_model not in RATE_MODELS:
            fail(f"rate_model must be one of {', '.join(RATE_MODELS)}, got {self.rate_model!r}")
        if self.mac not in MAC_MODELS:
            fail(f"mac must be one of {', '.join(MAC_MODELS)}, got {self.mac!r}")
        if self.polarization not in ("vertical", "horizontal"):
            fail(f"polarization must be vertical or horizontal, got {self.polarization!r}")
        if self.rate_model == "802.11n" and self.channel_width_mhz not in (20, 40):
            fail(f"channel_width_mhz must be 20 or 40 for 802.11n, got {self.channel_width_mhz}")
        for key in ("freq_mhz", "bandwidth_hz", "noise_w", "ref_distance_m", "base_height_m", "mobile_height_m",
                    "breakpoint_m", "antenna_height_m", "shadowing_decorrelation_m", "per_slope_db",
                    "ground_permittivity"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                fail(f"{key} must be a finite number > 0, got {value}")
        for key in ("shadowing_sigma_db", "hover_speed_mps", "rate_adaptation_s", "min_rate_bps", "overhead_bits"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0):
                fail(f"{key} must be a finite number >= 0, got {value}")
        if not 0 < self.mac_efficiency <= 1:
            fail(f"mac_efficiency must be in (0, 1], got {self.mac_efficiency}")
        if not 0 <= self.background_airtime < 1:
            fail(f"background_airtime must be in [0, 1), got {self.background_airtime}")
        if isinstance(self.retry_limit, bool) or not isinstance(self.retry_limit, int) \
                or not 0 <= self.retry_limit <= MAX_RETRY_LIMIT:
            fail(f"retry_limit must be an integer in 0..{MAX_RETRY_LIMIT} (802.11's retry limit), got "
                 f"{self.retry_limit!r}")

    @property
    def fading(self) -> bool:
        """Rician fading on: a K factor given and finite (inf: pure line of sight; TOML has no None)."""
        return self.rician_k_db is not None and math.isfinite(self.rician_k_db)

    @property
    def noise_dbm(self) -> float:
        return 10.0 * math.log10(self.noise_w) + 30.0

    @property
    def reference_loss_db(self) -> float:
        return self.ref_loss_db if self.ref_loss_db is not None else float(
            air_link.free_space_db(self.ref_distance_m, self.freq_mhz))

    def path_loss_db(self, distance_m, height_a_m=None, height_b_m=None):
        """Loss at distance (scalar or array); heights above ground matter to two-ray only."""
        d = distance_m
        if self.path_loss == "free-space":
            loss = air_link.free_space_db(d, self.freq_mhz)
        elif self.path_loss == "log-distance":
            loss = air_link.log_distance_db(d, self.reference_loss_db, self.exponent, self.ref_distance_m)
        elif self.path_loss == "dual-slope":
            loss = air_link.dual_slope_db(d, self.reference_loss_db, self.exponent, self.breakpoint_m,
                                       self.exponent_far, self.ref_distance_m)
        elif self.path_loss == "two-ray":
            ha = self.antenna_height_m if height_a_m is None else height_a_m
            hb = self.antenna_height_m if height_b_m is None else height_b_m
            loss = air_link.two_ray_db(d, ha, hb, self.freq_mhz, self.ground_permittivity, self.polarization)
        else:
            loss = air_link.hata_db(d, self.freq_mhz, self.base_height_m, self.mobile_height_m,
                                 self.path_loss.removeprefix("hata-"))
        return float(loss) if np.ndim(loss) == 0 else loss

    def received_dbm(self, distance_m, height_a_m=None, height_b_m=None):
        return self.tx_power_dbm - self.path_loss_db(distance_m, height_a_m, height_b_m)

    def median_snr_db(self, distance_m, height_a_m=None, height_b_m=None):
        return self.received_dbm(distance_m, height_a_m, height_b_m) - self.noise_dbm

    def capacity_bps(self, distance_m: float) -> float:
        """The median rate at a distance: no shadowing, no fading, the rate adaptation settled."""
        return float(air_link.link_rates(self, self.median_snr_db(distance_m)).goodput_bps[0])

    def usable(self, rate_bps: float) -> bool:
        """The one out-of-range rule: below min_rate_bps there is no link."""
        return rate_bps >= max(self.min_rate_bps, 1.0)

    def in_range(self, distance_m: float) -> bool:
        return self.usable(self.capacity_bps(distance_m))

    def range_m(self, step_m: float = 0.01, limit_m: float = 100_000.0) -> float:
        """The distance where the median rate falls below min_rate_bps (the first such distance from near to
        far: two-ray's nulls can make a link come back further out)."""
        if self.in_range(limit_m):
            return math.inf
        d = np.geomspace(air_link.MIN_DISTANCE_M, limit_m, 4000)
        rates = air_link.link_rates(self, self.median_snr_db(d)).goodput_bps
        first_out = int(np.argmax(rates < max(self.min_rate_bps, 1.0)))
        lo, hi = float(d[max(first_out - 1, 0)]), float(d[first_out])
        while hi - lo > step_m:
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if self.in_range(mid) else (lo, mid)
        return lo

    def validity(self) -> str:
        if not self.path_loss.startswith("hata"):
            return f"{self.path_loss} path loss"
        return ("Okumura-Hata is fitted for 150-1500 MHz, base antennas 30-200 m, mobiles 1-10 m and 1-20 km; "
                "between UAVs metres apart it is an extrapolation")

    def describe(self) -> str:
        """One line naming the model and the parameters that shape a result (for reports)."""
        if self.path_loss in ("log-distance", "dual-slope"):
            loss = (f"{self.path_loss} n {self.exponent:g}, PL({self.ref_distance_m:g} m) "
                    f"{self.reference_loss_db:.1f} dB")
            if self.path_loss == "dual-slope":
                loss += f", n {self.exponent_far:g} beyond {self.breakpoint_m:g} m"
        elif self.path_loss == "two-ray":
            loss = f"two-ray (ground permittivity {self.ground_permittivity:g}, {self.polarization})"
        else:
            loss = self.path_loss
        parts = [f"{self.name}: {loss} at {self.freq_mhz:g} MHz"]
        if self.shadowing_sigma_db:
            parts.append(f"shadowing sigma {self.shadowing_sigma_db:g} dB over {self.shadowing_decorrelation_m:g} m")
        if self.fading:
            parts.append(f"Rician K {self.rician_k_db:g} dB")
        if self.rate_model == "802.11n":
            guard = "short" if self.short_guard_interval else "long"
            parts.append(f"802.11n MCS 0-7 ({self.channel_width_mhz} MHz, {guard} "
                         f"GI, offset {self.mcs_offset_db:g} dB, adaptation {self.rate_adaptation_s:g} s)")
        else:
            parts.append(f"Shannon over {self.bandwidth_hz / 1e6:g} MHz")
        if self.mac == "802.11":  # the medium's own costs: the efficiency is not used
            parts.append(f"the 802.11 MAC frame by frame (channel access, preamble and block ack per aggregate, "
                         f"retry limit {self.retry_limit})")
        elif self.rate_model == "802.11n":
            parts[-1] += f", MAC efficiency {self.mac_efficiency:g}"
        if self.background_airtime:
            parts.append(f"{self.background_airtime:.0%} background airtime")
        if self.overhead_bits:
            parts.append(f"{self.overhead_bits:g} bits of overhead per transfer")
        if self.replay_file:
            parts.append(f"recorded pairs replayed from {self.replay_file}")
        return "; ".join(parts)


def noise_w(bandwidth_hz: float, noise_figure_db: float) -> float:
    """Thermal noise (-174 dBm/Hz) in a bandwidth, through a receiver's noise figure, in W."""
    return 10.0 ** ((-174.0 + 10.0 * math.log10(bandwidth_hz) + noise_figure_db - 30.0) / 10.0)


PRESETS = {
    "paper-sim": ChannelModel(
        name="paper-sim", path_loss="hata-urban", freq_mhz=1200.0, bandwidth_hz=1200e6, tx_power_dbm=20.0,
        noise_w=1.1e-35, base_height_m=30.0, mobile_height_m=1.5,
        notes="the research's simulation: Hata-Okumura and Shannon, deterministic",
        sources="the research's simulation values (f 1200 MHz, W 1200 MHz, N0 1.1e-35 W); its Hata environment, "
                "antenna heights and transmit power are not given: small/medium city, h_b 30 m, h_m 1.5 m, "
                "20 dBm assumed"),
    "wifi-flight": ChannelModel(
        name="wifi-flight", path_loss="log-distance", freq_mhz=2437.0, bandwidth_hz=20e6, tx_power_dbm=15.0,
        noise_w=noise_w(20e6, 6.0), exponent=3.8, ref_distance_m=1.0, ref_loss_db=55.5,
        shadowing_sigma_db=4.0, shadowing_decorrelation_m=5.0, rician_k_db=6.0, hover_speed_mps=0.2,
        rate_model="802.11n", mcs_offset_db=-4.0, rate_adaptation_s=0.35, mac_efficiency=0.6,
        min_rate_bps=1e6, seed=1,
        notes="2.4 GHz 802.11n between quadrotors at ~3 m: median ~22 Mbit/s at 9-10 m, out of range near 25 m",
        sources="range and rates: the research's flight tests (consumer 2.4 GHz routers, throughput ~0 at 20-25 m, "
                "static links at 9-10 m); n 3.8 and PL(1 m) 55.5 dB fitted to them (15 dB over free space: "
                "airframes, antenna patterns, consumer radios); shadowing sigma 4 dB (inside the 2.8-5.3 dB "
                "published for open-field air-to-ground links) decorrelating over 5 m (Gudmundson's model, "
                "a short distance for low altitude); Rician K 6 dB (low-altitude line of sight with ground "
                "scatter); MCS thresholds: IEEE 802.11n minimum sensitivities less 4 dB for a practical "
                "receiver; adaptation 0.35 s (a Minstrel-style moving average every 100 ms); MAC efficiency "
                "0.6 (TCP over 802.11n without aggregation); noise figure 6 dB; hover wander 0.2 m/s "
                "(GPS position hold)"),
}
# Over open fields the same radios (the rate side as wifi-flight) see little more than free space.
PRESETS["wifi-open-field"] = dataclasses.replace(
    PRESETS["wifi-flight"], name="wifi-open-field", tx_power_dbm=20.0, exponent=2.2, ref_loss_db=None,
    shadowing_decorrelation_m=10.0, rician_k_db=10.0,
    notes="2.4 GHz 802.11n over open fields: free-space loss at 1 m, n 2.2",
    sources="n 2.2 and sigma 4 dB: inside the published open-field air-to-ground ranges (n about 2.0-2.5, "
            "shadowing sigma 2.8-5.3 dB); PL(1 m) free space; Rician K 10 dB (clear line of sight); 20 dBm (the "
            "2.4 GHz EIRP limit of 100 mW); the rate side as wifi-flight")
