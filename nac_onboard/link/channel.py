"""Channel models (pure): path loss, received power and Shannon capacity between two vehicles (DESIGN.md 6).

    S = S_t - P_L (dBm);  C = W log2(1 + 10^((S - 30)/10) / N0)  (bit/s, W in Hz, N0 noise power in W)

Path-loss models:
  free-space        20 log10(d_m) + 20 log10(f_Hz) - 147.55
  log-distance      PL(d0) + 10 n log10(d / d0)   (PL(d0) defaults to free space at d0)
  hata-urban        Okumura-Hata, small or medium city: D + E log10(d_km), a(h_m) for a small/medium city
  hata-large-city   a(h_m) for a large city (f >= 400 MHz form; the f <= 200 MHz form below 300 MHz)
  hata-suburban     urban - 2 (log10(f/28))^2 - 5.4
  hata-rural        urban - 4.78 (log10 f)^2 + 18.33 log10 f - 40.94  (open area)
with D = 69.55 + 26.16 log10 f - 13.82 log10 h_b - a(h_m), E = 44.9 - 6.55 log10 h_b (f in MHz). Hata is
defined for 150-1500 MHz, h_b 30-200 m, h_m 1-10 m, d 1-20 km; UAVs metres apart are far outside that, which
`ChannelModel.validity` says, so the log-distance and free-space models are there too.

Below min_rate_bps a link is out of range: emulated transfers do not happen.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

from nac_onboard.errors import BadInput
from nac_onboard.tomlfile import read_toml, to_dataclass, write_toml

PATH_LOSS_MODELS = ("free-space", "log-distance", "hata-urban", "hata-large-city", "hata-suburban", "hata-rural")
MIN_DISTANCE_M = 0.1  # closer than this the formulas are meaningless; distances are clamped


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
    exponent: float = 2.0  # log-distance n
    ref_distance_m: float = 1.0  # log-distance d0
    ref_loss_db: float | None = None  # log-distance PL(d0); None = free space at d0
    base_height_m: float = 30.0  # Hata h_b
    mobile_height_m: float = 1.5  # Hata h_m
    min_rate_bps: float = 0.0
    max_rate_bps: float | None = None  # a radio's top rate (Shannon has none)
    # What each transfer costs beyond its payload, as bits at the link's rate: headers, MAC contention, TCP
    # acknowledgements, the MPI envelope and the stacks' own time on a companion computer. 0 = payload only.
    overhead_bits: float = 0.0
    notes: str = ""

    def __post_init__(self):
        if self.path_loss not in PATH_LOSS_MODELS:
            raise ChannelError(f"channel {self.name!r}: path_loss must be one of {', '.join(PATH_LOSS_MODELS)}, "
                               f"got {self.path_loss!r}")
        for key in ("freq_mhz", "bandwidth_hz", "noise_w", "ref_distance_m", "base_height_m", "mobile_height_m"):
            if not getattr(self, key) > 0:
                raise ChannelError(f"channel {self.name!r}: {key} must be > 0, got {getattr(self, key)}")

    def path_loss_db(self, distance_m: float) -> float:
        d = max(distance_m, MIN_DISTANCE_M)
        if self.path_loss == "free-space":
            return free_space_loss_db(d, self.freq_mhz)
        if self.path_loss == "log-distance":
            ref = self.ref_loss_db if self.ref_loss_db is not None else free_space_loss_db(self.ref_distance_m,
                                                                                          self.freq_mhz)
            return ref + 10.0 * self.exponent * math.log10(d / self.ref_distance_m)
        return hata_loss_db(d, self.freq_mhz, self.base_height_m, self.mobile_height_m,
                            self.path_loss.removeprefix("hata-"))

    def received_dbm(self, distance_m: float) -> float:
        return self.tx_power_dbm - self.path_loss_db(distance_m)

    def capacity_bps(self, distance_m: float) -> float:
        rate = shannon_capacity_bps(self.received_dbm(distance_m), self.bandwidth_hz, self.noise_w)
        return min(rate, self.max_rate_bps) if self.max_rate_bps else rate

    def usable(self, rate_bps: float) -> bool:
        """The one out-of-range rule: below min_rate_bps there is no link (emulated transfers do not happen)."""
        return rate_bps >= self.min_rate_bps

    def in_range(self, distance_m: float) -> bool:
        return self.usable(self.capacity_bps(distance_m))

    def range_m(self, step_m: float = 0.01, limit_m: float = 100_000.0) -> float:
        """The distance where the capacity falls below min_rate_bps (capacity falls with distance)."""
        lo, hi = MIN_DISTANCE_M, limit_m
        if self.in_range(hi):
            return math.inf
        while hi - lo > step_m:
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if self.in_range(mid) else (lo, mid)
        return lo

    def validity(self) -> str:
        if not self.path_loss.startswith("hata"):
            return f"{self.path_loss} path loss"
        return ("Okumura-Hata is fitted for 150-1500 MHz, base antennas 30-200 m, mobiles 1-10 m and 1-20 km; "
                "between UAVs metres apart it is an extrapolation")


def free_space_loss_db(distance_m: float, freq_mhz: float) -> float:
    return 20.0 * math.log10(distance_m) + 20.0 * math.log10(freq_mhz * 1e6) - 147.55


def hata_loss_db(distance_m: float, freq_mhz: float, base_height_m: float, mobile_height_m: float,
                 environment: str) -> float:
    f, hb, hm = freq_mhz, base_height_m, mobile_height_m
    lf = math.log10(f)
    if environment == "large-city":
        if f >= 300:
            a_hm = 3.2 * math.log10(11.75 * hm) ** 2 - 4.97
        else:
            a_hm = 8.29 * math.log10(1.54 * hm) ** 2 - 1.1
    else:
        a_hm = (1.1 * lf - 0.7) * hm - (1.56 * lf - 0.8)
    d_term = 69.55 + 26.16 * lf - 13.82 * math.log10(hb) - a_hm
    e_term = 44.9 - 6.55 * math.log10(hb)
    urban = d_term + e_term * math.log10(distance_m / 1000.0)
    if environment in ("urban", "large-city"):
        return urban
    if environment == "suburban":
        return urban - 2.0 * math.log10(f / 28.0) ** 2 - 5.4
    if environment == "rural":
        return urban - 4.78 * lf ** 2 + 18.33 * lf - 40.94
    raise ChannelError(f"unknown Hata environment {environment!r}")


def shannon_capacity_bps(received_dbm: float, bandwidth_hz: float, noise_w: float) -> float:
    signal_w = 10.0 ** ((received_dbm - 30.0) / 10.0)
    return bandwidth_hz * math.log2(1.0 + signal_w / noise_w)


#: paper-sim: the research's simulation (f 1200 MHz, W 1200 MHz, N0 1.1e-35 W; Hata-Okumura, whose
#: environment and antenna heights the paper does not give: small/medium city, h_b 30 m, h_m 1.5 m, 20 dBm).
#: wifi-flight: consumer 2.4 GHz Wi-Fi as the flight tests saw it, throughput falling to ~0 near 20-25 m: a
#: log-distance fit (n 4.1, 69.6 dB at 1 m: antenna, body and implementation losses included) over -95 dBm of
#: noise in 20 MHz, capped at an 802.11n link's 72 Mbit/s, out of range below 1 Mbit/s (about 22 m). Its
#: 2 Mbit of overhead per transfer reproduces the flight's pace (static: 640 iterations in 200 s, about 0.3 s
#: each, at 9-10 m, i.e. ~19 Mbit/s): what MPI, TCP and Python cost on the Jetsons over Wi-Fi, not payload.
PRESETS = {
    "paper-sim": ChannelModel(
        name="paper-sim", path_loss="hata-urban", freq_mhz=1200.0, bandwidth_hz=1200e6, tx_power_dbm=20.0,
        noise_w=1.1e-35, base_height_m=30.0, mobile_height_m=1.5,
        notes="the research's simulation values; Hata environment, heights and transmit power assumed"),
    "wifi-flight": ChannelModel(
        name="wifi-flight", path_loss="log-distance", freq_mhz=2437.0, bandwidth_hz=20e6, tx_power_dbm=15.0,
        noise_w=10 ** ((-95.0 - 30.0) / 10.0), exponent=4.1, ref_distance_m=1.0, ref_loss_db=69.6,
        min_rate_bps=1e6, max_rate_bps=72e6, overhead_bits=2e6,
        notes="fitted to the flight tests: throughput near 0 at 20-25 m, ~0.3 s iterations when static"),
}


def load_channel(name_or_path: str) -> ChannelModel:
    """A preset by name, or a TOML file of ChannelModel fields (what `nac-ground logs calibrate` writes)."""
    if name_or_path in PRESETS:
        return PRESETS[name_or_path]
    path = Path(name_or_path)
    if not path.exists():
        raise ChannelError(f"channel {name_or_path!r}: not a preset ({', '.join(PRESETS)}) nor a file")
    values = read_toml(path, "channel model", ChannelError)
    values.setdefault("name", path.stem)
    return to_dataclass(ChannelModel, values, str(path), ChannelError)


def save_channel(model: ChannelModel, path: str | Path) -> None:
    write_toml(path, dataclasses.asdict(model))
