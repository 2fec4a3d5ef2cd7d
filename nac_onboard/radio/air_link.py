"""The air-to-air link between vehicles (pure, vectorised over pairs, seeded): path loss, shadowing, fading,
802.11n rate selection and packet errors (DESIGN.md 6). No I/O: the kernel shaper and the sleep emulation step
it with positions and read rates and losses; the SITL's telemetry radio (sitl.telemetry_radio) shares its
formulas.

Per pair and step (time step dt, the pair's motion since the last step):
  SNR (dB)   = P_t - PL(d, h_a, h_b) + shadowing + fading - noise
  shadowing  log-normal, correlated over the distance the pair's ends moved (Gudmundson 1991): a function of that
             distance, not of how often the pair is stepped (PathShadowing); a static pair keeps its offset
  fading     Rician power |h|^2, h = sqrt(K/(K+1)) + sqrt(1/(K+1)) g, g complex Gaussian correlated in time by
             Clarke's rho = J0(2 pi f_D dt), f_D = (speed of both ends, at least a hover's) / wavelength
  rate       Shannon (the research's) or an 802.11n MCS: the rate adaptation picks, from an estimate of the SNR
             that lags the channel (time constant rate_adaptation_s), the MCS with the best expected
             throughput; the frame error rate at the true SNR is a logistic waterfall through 10 % at the MCS's
             threshold; goodput = PHY rate x MAC efficiency x (1 - PER) x (1 - background airtime)
  loss       what reaches IP: every MAC attempt lost, the first half of the retries at the chosen MCS and the
             rest at MCS 0 (the last entry of a Minstrel-style retry chain)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nac_onboard.radio.medium import saturated_goodput_bps

C_MPS = 299_792_458.0
MIN_DISTANCE_M = 0.1  # closer than this the formulas are meaningless; distances are clamped

# IEEE 802.11n (HT), one spatial stream, MCS 0-7: PHY rates in Mbit/s by (channel width MHz, short guard).
HT_RATES_MBPS = {
    (20, False): (6.5, 13.0, 19.5, 26.0, 39.0, 52.0, 58.5, 65.0),
    (20, True): (7.2, 14.4, 21.7, 28.9, 43.3, 57.8, 65.0, 72.2),
    (40, False): (13.5, 27.0, 40.5, 54.0, 81.0, 108.0, 121.5, 135.0),
    (40, True): (15.0, 30.0, 45.0, 60.0, 90.0, 120.0, 135.0, 150.0),
}
# SNR (dB) at 10 % frame error per MCS: the standard's minimum input sensitivities (20 MHz: -82, -79, -77, -74,
# -70, -66, -65, -64 dBm; 40 MHz 3 dB higher, as its noise is) over the noise floor they assume (-174 dBm/Hz +
# 10 log10 W + a 10 dB noise figure, i.e. -91 dBm in 20 MHz). Real radios do better; mcs_offset_db shifts them.
HT_SNR_THRESHOLDS_DB = np.array([9.0, 12.0, 14.0, 17.0, 21.0, 25.0, 26.0, 27.0])
LN9 = math.log(9.0)


# ---- path loss (dB), vectorised -----------------------------------------------------------------------------
def free_space_db(distance_m, freq_mhz: float):
    d = np.maximum(np.asarray(distance_m, float), MIN_DISTANCE_M)
    return 20.0 * np.log10(d) + 20.0 * math.log10(freq_mhz * 1e6) - 147.55


def log_distance_db(distance_m, ref_loss_db: float, exponent: float, ref_distance_m: float = 1.0):
    d = np.maximum(np.asarray(distance_m, float), MIN_DISTANCE_M)
    return ref_loss_db + 10.0 * exponent * np.log10(d / ref_distance_m)


def dual_slope_db(distance_m, ref_loss_db: float, exponent: float, breakpoint_m: float, exponent_far: float,
                  ref_distance_m: float = 1.0):
    """n up to the breakpoint, n_far beyond it, continuous at the breakpoint."""
    d = np.maximum(np.asarray(distance_m, float), MIN_DISTANCE_M)
    near = ref_loss_db + 10.0 * exponent * np.log10(np.minimum(d, breakpoint_m) / ref_distance_m)
    return near + 10.0 * exponent_far * np.log10(np.maximum(d, breakpoint_m) / breakpoint_m)


def ground_reflection(sin_grazing, permittivity: float, polarization: str):
    """Fresnel reflection coefficient of flat ground (relative permittivity, lossless)."""
    cos2 = 1.0 - sin_grazing ** 2
    root = np.sqrt(permittivity - cos2)
    if polarization == "vertical":
        return (permittivity * sin_grazing - root) / (permittivity * sin_grazing + root)
    return (sin_grazing - root) / (sin_grazing + root)


def two_ray_db(distance_m, height_a_m, height_b_m, freq_mhz: float, permittivity: float = 15.0,
               polarization: str = "vertical"):
    """Exact two-ray ground reflection: the direct ray and one reflected off flat ground, summed in phase.
    distance_m is the direct (3-D) distance; heights are above the ground."""
    d = np.maximum(np.asarray(distance_m, float), MIN_DISTANCE_M)
    ha = np.maximum(np.asarray(height_a_m, float), 0.01)
    hb = np.maximum(np.asarray(height_b_m, float), 0.01)
    wavelength = C_MPS / (freq_mhz * 1e6)
    horizontal = np.sqrt(np.maximum(d ** 2 - (ha - hb) ** 2, 0.0))
    reflected = np.sqrt(horizontal ** 2 + (ha + hb) ** 2)
    gamma = ground_reflection((ha + hb) / reflected, permittivity, polarization)
    k = 2.0 * math.pi / wavelength
    field = np.exp(-1j * k * d) / d + gamma * np.exp(-1j * k * reflected) / reflected
    return -20.0 * np.log10(wavelength / (4.0 * math.pi) * np.abs(field))


def hata_db(distance_m, freq_mhz: float, base_height_m: float, mobile_height_m: float, environment: str):
    """Okumura-Hata (the research's), small/medium or large city, suburban or open (rural) area."""
    d = np.maximum(np.asarray(distance_m, float), MIN_DISTANCE_M)
    f, hb, hm = freq_mhz, base_height_m, mobile_height_m
    lf = math.log10(f)
    if environment == "large-city":
        a_hm = 3.2 * math.log10(11.75 * hm) ** 2 - 4.97 if f >= 300 else 8.29 * math.log10(1.54 * hm) ** 2 - 1.1
    else:
        a_hm = (1.1 * lf - 0.7) * hm - (1.56 * lf - 0.8)
    urban = (69.55 + 26.16 * lf - 13.82 * math.log10(hb) - a_hm
             + (44.9 - 6.55 * math.log10(hb)) * np.log10(d / 1000.0))
    if environment in ("urban", "large-city"):
        return urban
    if environment == "suburban":
        return urban - 2.0 * math.log10(f / 28.0) ** 2 - 5.4
    if environment == "rural":
        return urban - 4.78 * lf ** 2 + 18.33 * lf - 40.94
    raise ValueError(f"unknown Hata environment {environment!r}")


# ---- rate -------------------------------------------------------------------------------------------------
def shannon_bps(snr_db, bandwidth_hz: float):
    return bandwidth_hz * np.log2(1.0 + 10.0 ** (np.asarray(snr_db, float) / 10.0))


def frame_error_rate(snr_db, threshold_db, slope_db: float):
    """A logistic waterfall through 10 % at the threshold; slope_db sets its width (90 % -> 10 % over 4.4
    slope_db)."""
    x = (np.asarray(snr_db, float) - threshold_db) / slope_db + LN9
    return 1.0 / (1.0 + np.exp(np.clip(x, -60.0, 60.0)))


def bessel_j0(x):
    """J0 by its integral (1/pi) int_0^pi cos(x sin t) dt, to ~1e-9 for |x| < 30: enough for a correlation."""
    t = (np.arange(64) + 0.5) * (math.pi / 64)
    return np.cos(np.multiply.outer(np.asarray(x, float), np.sin(t))).mean(axis=-1)


def complex_normal(rng: np.random.Generator, shape) -> np.ndarray:
    """Circular complex Gaussian draws of unit power: the scattered part of a fading channel."""
    return (rng.normal(size=shape) + 1j * rng.normal(size=shape)) / math.sqrt(2.0)


def rician_fade_db(k_db: float, scatter: np.ndarray) -> np.ndarray:
    """A Rician channel's power gain (dB, unit mean power) with line-of-sight factor K and scattered part g:
    |sqrt(K/(K+1)) + sqrt(1/(K+1)) g|^2."""
    k = 10.0 ** (k_db / 10.0)
    power = np.abs(math.sqrt(k / (k + 1)) + math.sqrt(1 / (k + 1)) * scatter) ** 2
    return 10.0 * np.log10(np.maximum(power, 1e-12))


def rician_power_moments(k_linear: float) -> tuple[float, float]:
    """Mean and variance of |h|^2 for a Rician channel of unit mean power."""
    return 1.0, (2.0 * k_linear + 1.0) / (k_linear + 1.0) ** 2


@dataclass(frozen=True)
class Sample:
    """Every pair at one step."""

    snr_db: np.ndarray
    mcs: np.ndarray  # -1 with the Shannon rate model
    phy_bps: np.ndarray
    per: np.ndarray  # frame error rate at the chosen rate
    goodput_bps: np.ndarray  # what a transfer gets: the pair's rate
    loss: np.ndarray  # packets lost to IP after the MAC's retries (1 when out of range)
    in_range: np.ndarray
    fallback_bps: np.ndarray | None = None  # the retry chain's last rate (MCS 0), for a frame-level medium
    fallback_per: np.ndarray | None = None  # its frame error rate


SHADOW_GRID_STEPS = 20  # grid points per decorrelation distance: linear interpolation between two points
# exp(-1/20) correlated keeps 98.8 % of sigma halfway between them (variance (1 + rho) / 2)


class PathShadowing:
    """Gudmundson's shadowing as a function of how far a pair's ends have moved: an AR(1) sequence on a grid of
    d_corr / SHADOW_GRID_STEPS along that path, s[k+1] = rho s[k] + sqrt(1 - rho^2) sigma w[k+1], interpolated
    linearly. Each w[k] is a hash of (seed, pair, k), so the offset after a path is the same however the path was
    stepped. Stepped per update with fresh draws, as it was, a hovering pair's offset was whatever the updates
    during its climb had drawn, and the updates' timing changes with the host's load and the speed-up: the same
    static flight saw a 57 or a 32 Mbit/s link (MCS 7 or 4) from run to run."""

    def __init__(self, sigma_db: float, decorrelation_m: float, pairs: int, seed: int):
        self.sigma_db, self.seed = sigma_db, np.uint64(seed)
        self.grid_m = decorrelation_m / SHADOW_GRID_STEPS
        self.rho = math.exp(-1.0 / SHADOW_GRID_STEPS)
        self.pair = np.arange(pairs, dtype=np.uint64)
        self.travelled_m = np.zeros(pairs)
        self.index = np.zeros(pairs, dtype=np.int64)  # the grid point at or before travelled_m
        self.keep = math.sqrt(1 - self.rho ** 2) * sigma_db  # the innovation's scale
        self.here = sigma_db * self._w(np.zeros(pairs, dtype=np.int64))
        self.ahead = self.rho * self.here + self.keep * self._w(np.ones(pairs, dtype=np.int64))
        self.db = self.here.copy()

    def _w(self, k: np.ndarray) -> np.ndarray:
        """Standard normal draws for grid points k (pairs first; Box-Muller over two splitmix64 hashes)."""
        pair = self.pair.reshape((-1,) + (1,) * (k.ndim - 1))
        counter = k.astype(np.uint64) * np.uint64(2)
        u = [(hashed_u64(self.seed, pair, counter + np.uint64(half)) >> np.uint64(11)).astype(float) * 2.0 ** -53
             for half in (0, 1)]
        return np.sqrt(-2.0 * np.log1p(-u[0])) * np.cos(2.0 * math.pi * u[1])

    def advance(self, moved_m) -> None:
        if self.sigma_db <= 0:
            return
        self.travelled_m = self.travelled_m + np.maximum(np.asarray(moved_m, float), 0.0)
        target = np.floor(self.travelled_m / self.grid_m).astype(np.int64)
        passed = target - self.index
        if passed.max(initial=0) > 0:
            rounds = int(passed.max())
            w = self._w(self.index[:, None] + 2 + np.arange(rounds)[None, :])  # every new point's draw at once
            for r in range(rounds):  # one grid point a round, for every pair that passed that many
                behind = passed > r
                fresh = self.rho * self.ahead + self.keep * w[:, r]
                self.here = np.where(behind, self.ahead, self.here)
                self.ahead = np.where(behind, fresh, self.ahead)
            self.index = target
        self.db = self.here + (self.travelled_m / self.grid_m - self.index) * (self.ahead - self.here)


def hashed_u64(seed: np.uint64, stream: np.ndarray, counter: np.ndarray) -> np.ndarray:
    """A counter-based uniform 64-bit value per element (splitmix64's finaliser, twice, over the seed, the stream
    and the counter, each spread by its own odd constant): the same for the same inputs on every host."""
    with np.errstate(over="ignore"):
        x = (seed + np.asarray(stream, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             + np.asarray(counter, dtype=np.uint64) * np.uint64(0xD1B54A32D192ED03))
        for _ in range(2):
            x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            x = x ^ (x >> np.uint64(31))
    return x


class Radio:
    """The time-varying part of a set of pairs (shadowing, fading, rate adaptation), stepped by the caller.
    model is a nac_onboard.radio.channel.ChannelModel."""

    def __init__(self, model, pairs: int, seed: int | None = None):
        self.model, self.pairs = model, pairs
        self.rng = np.random.default_rng(model.seed if seed is None else seed)
        self.shadowing = PathShadowing(model.shadowing_sigma_db, model.shadowing_decorrelation_m, pairs,
                                       int(self.rng.integers(2 ** 63)))
        self.scatter = complex_normal(self.rng, pairs)
        self.snr_estimate_db: np.ndarray | None = None

    @property
    def shadow_db(self) -> np.ndarray:
        return self.shadowing.db

    def step(self, dt_s: float, distance_m, height_a_m=None, height_b_m=None, moved_m=None,
             speed_mps=None) -> Sample:
        """Advance dt_s: moved_m is how far the pair's two ends moved in it, speed_mps their summed speed."""
        m = self.model
        distance_m = np.asarray(distance_m, float)
        moved = np.zeros(self.pairs) if moved_m is None else np.asarray(moved_m, float)
        speed = np.zeros(self.pairs) if speed_mps is None else np.asarray(speed_mps, float)
        self.shadowing.advance(moved)
        fade_db = np.zeros(self.pairs)
        if m.fading:
            if dt_s > 0:
                doppler_hz = np.maximum(speed, m.hover_speed_mps) * m.freq_mhz * 1e6 / C_MPS
                rho = np.clip(bessel_j0(2.0 * math.pi * doppler_hz * dt_s), 0.0, 1.0)
                self.scatter = rho * self.scatter + np.sqrt(1 - rho ** 2) * complex_normal(self.rng, self.pairs)
            fade_db = rician_fade_db(m.rician_k_db, self.scatter)
        snr_db = m.median_snr_db(distance_m, height_a_m, height_b_m) + self.shadow_db + fade_db
        if self.snr_estimate_db is None or m.rate_adaptation_s <= 0:
            self.snr_estimate_db = snr_db.copy()
        else:
            alpha = 1.0 - math.exp(-dt_s / m.rate_adaptation_s)
            self.snr_estimate_db = self.snr_estimate_db + alpha * (snr_db - self.snr_estimate_db)
        return link_rates(m, snr_db, self.snr_estimate_db)


def link_rates(m, snr_db, snr_estimate_db=None) -> Sample:
    """Rates and losses at a true SNR, the rate chosen from the estimate (the true SNR when none)."""
    snr_db = np.atleast_1d(np.asarray(snr_db, float))
    estimate = snr_db if snr_estimate_db is None else np.atleast_1d(np.asarray(snr_estimate_db, float))
    airtime = 1.0 - m.background_airtime
    if m.rate_model == "shannon":
        phy = shannon_bps(snr_db, m.bandwidth_hz)
        if m.max_rate_bps:
            phy = np.minimum(phy, m.max_rate_bps)
        per = np.zeros_like(phy)
        mcs = np.full(phy.shape, -1)
        loss = np.zeros_like(phy)
        fallback_bps, fallback_per = phy, per
    else:
        rates = np.array(HT_RATES_MBPS[(m.channel_width_mhz, m.short_guard_interval)]) * 1e6
        thresholds = HT_SNR_THRESHOLDS_DB + m.mcs_offset_db
        expected = rates * (1.0 - frame_error_rate(estimate[:, None], thresholds, m.per_slope_db))
        mcs = np.argmax(expected, axis=1)
        phy = rates[mcs]
        per = frame_error_rate(snr_db, thresholds[mcs], m.per_slope_db)
        first = (m.retry_limit + 1) // 2
        fallback_bps = np.full(phy.shape, rates[0])
        fallback_per = frame_error_rate(snr_db, thresholds[0], m.per_slope_db)
        loss = per ** first * fallback_per ** (m.retry_limit + 1 - first)
    if m.mac == "802.11":
        efficiency = np.array([saturated_goodput_bps(float(r)) / r if r > 0 else 0.0 for r in np.round(phy, -3).flat])
        goodput = phy * efficiency.reshape(phy.shape) * (1.0 - per) * airtime
    else:
        goodput = phy * m.mac_efficiency * (1.0 - per) * airtime
    in_range = goodput >= max(m.min_rate_bps, 1.0)
    return Sample(snr_db, mcs, phy, per, np.where(in_range, goodput, 0.0), np.where(in_range, loss, 1.0),
                  in_range, fallback_bps, fallback_per)


class AirRadio:
    """N vehicles' radios: every unordered pair (i < j) stepped from positions in one metric frame; a pair's
    link is reciprocal (one shadowing and fading per pair)."""

    def __init__(self, model, vehicles: int, seed: int | None = None):
        self.n = vehicles
        self.i, self.j = np.triu_indices(vehicles, k=1)
        self.radio = Radio(model, len(self.i), seed)
        self._last: tuple[float, np.ndarray] | None = None

    def step(self, t_s: float, positions_m, heights_m=None) -> tuple[np.ndarray, Sample]:
        """(pair distances, the pairs' sample); positions (N, 3) in metres, heights above ground (N,)."""
        positions_m = np.asarray(positions_m, float)
        distance = np.linalg.norm(positions_m[self.i] - positions_m[self.j], axis=1)
        dt_s, moved, speed = 0.0, None, None
        if self._last is not None:
            dt_s = max(t_s - self._last[0], 0.0)
            step_m = np.linalg.norm(positions_m - self._last[1], axis=1)
            moved = step_m[self.i] + step_m[self.j]
            speed = moved / dt_s if dt_s > 0 else np.zeros_like(moved)
        self._last = (t_s, positions_m.copy())
        h = None if heights_m is None else np.asarray(heights_m, float)
        sample = self.radio.step(dt_s, distance, None if h is None else h[self.i], None if h is None else h[self.j],
                                 moved, speed)
        return distance, sample

    def matrix(self, values, diagonal: float = 0.0) -> np.ndarray:
        out = np.full((self.n, self.n), diagonal, dtype=float)
        out[self.i, self.j] = out[self.j, self.i] = values
        return out


def rate_band(model, distance_m, draws: int = 2000, seed: int = 0) -> dict[str, np.ndarray]:
    """Throughput against distance as a band: at each distance, `draws` independent pairs (their own shadowing
    and fading, the rate adaptation settled) give the median and the 2.5 and 97.5 percentiles, with the median
    link's MCS (the steps)."""
    d = np.atleast_1d(np.asarray(distance_m, float))
    radio = Radio(model, draws * len(d), seed)
    sample = radio.step(0.0, np.repeat(d, draws))
    rates = sample.goodput_bps.reshape(len(d), draws)
    median = link_rates(model, model.median_snr_db(d))
    return {"distance_m": d, "mcs": median.mcs, "median_bps": np.median(rates, axis=1),
            "low_bps": np.percentile(rates, 2.5, axis=1), "high_bps": np.percentile(rates, 97.5, axis=1),
            "in_range_fraction": sample.in_range.reshape(len(d), draws).mean(axis=1)}
