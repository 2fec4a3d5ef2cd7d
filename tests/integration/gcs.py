"""Test-side ground station: the product's MAVLink client on a vehicle's SITL port."""

from nac_onboard.mavlink_client import M, VehicleClient
from sitl.demo import waypoint_mission

__all__ = ["Gcs", "M", "waypoint_mission"]


class Gcs(VehicleClient):
    def __init__(self, port: int, sysid: int = 1, source_system: int = 255):
        super().__init__(f"udpin:127.0.0.1:{port}", sysid=sysid, source_system=source_system)
