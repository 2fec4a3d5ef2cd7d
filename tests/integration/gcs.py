"""Test-side ground station: the product's MAVLink client on a vehicle's SITL port."""

from missions.model import MavCmd
from nac_onboard.mavlink.client import VehicleClient
from nac_onboard.mavlink.dialect import M

__all__ = ["Gcs", "M", "take_off"]


class Gcs(VehicleClient):
    def __init__(self, port: int, sysid: int = 1, source_system: int = 255):
        super().__init__(f"udpin:127.0.0.1:{port}", sysid=sysid, source_system=source_system)


def take_off(gcs: Gcs, alt_m: float) -> None:
    """Arm, take off in GUIDED and wait for the vehicle to say it reached the altitude."""
    assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert gcs.command(MavCmd.NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt_m) == M.MAV_RESULT_ACCEPTED
    assert gcs.recv("STATUSTEXT", 10.0, lambda m: "Takeoff complete" in m.text) is not None
