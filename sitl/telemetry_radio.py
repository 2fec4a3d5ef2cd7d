"""The SITL's ground telemetry link: the radio between the ground station and each simulated vehicle (a
915 MHz SiK-class modem), as data. Pure: the simulator (sitl.server, `--telemetry-radio`) asks it which share
of MAVLink frames a vehicle at a distance and height loses. Real vehicles have the modem itself; this model is
SITL-only, so it lives here rather than beside the vehicles' air-to-air radio (nac_onboard.radio), whose
two-ray and frame-error formulas it shares.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from nac_onboard.radio.air_link import frame_error_rate, two_ray_db


@dataclass(frozen=True)
class TelemetryRadio:
    """The MAVLink ground link's radio (a 915 MHz SiK-class modem): each frame is lost with the frame error rate
    at the received power, over two-ray ground reflection between the ground station's antenna and the
    vehicle's. Sensitivity is where 10 % of frames fail."""

    name: str
    freq_mhz: float
    tx_power_dbm: float
    antenna_gain_dbi: float  # each end
    system_loss_db: float  # cables, antenna orientation, the airframe, interference: a field fade margin
    sensitivity_dbm: float
    slope_db: float
    ground_antenna_m: float
    sources: str = ""

    def received_dbm(self, distance_m, vehicle_height_m):
        return (self.tx_power_dbm + 2 * self.antenna_gain_dbi - self.system_loss_db
                - two_ray_db(distance_m, self.ground_antenna_m, vehicle_height_m, self.freq_mhz))

    def frame_loss(self, distance_m, vehicle_height_m):
        return frame_error_rate(self.received_dbm(distance_m, vehicle_height_m), self.sensitivity_dbm,
                                self.slope_db)

    def range_m(self, vehicle_height_m: float, loss: float = 0.5) -> float:
        """The first distance (1 m steps) where `loss` of the frames fail."""
        d = np.arange(1.0, 100_000.0, 1.0)
        beyond = self.frame_loss(d, vehicle_height_m) >= loss
        return float(d[np.argmax(beyond)]) if beyond.any() else math.inf


TELEMETRY_RADIOS = {
    "sik-915": TelemetryRadio(
        name="sik-915", freq_mhz=915.0, tx_power_dbm=20.0, antenna_gain_dbi=2.0, system_loss_db=25.0,
        sensitivity_dbm=-105.0, slope_db=1.5, ground_antenna_m=1.5,
        sources="SiK firmware radios (3DR / Holybro / RFD900-class at 100 mW): 20 dBm, 2 dBi dipoles, about "
                "-105 dBm sensitivity at the default 64 kbit/s air rate (-121 dBm at 2 kbit/s in the modem's "
                "data sheet, ~8 dB lost per doubling of the rate); a 25 dB field margin so stock radios reach "
                "the 1-2 km that users report rather than the free-space tens of kilometres"),
}
