"""Test-side ground station: the product's MAVLink client on a vehicle's SITL port."""

from missions.model import Frame, MavCmd, MissionItem
from nac_onboard.mavlink_client import M, VehicleClient
from sitl.geodesy import Home, offset_home

__all__ = ["Gcs", "M", "take_off", "waypoint_mission"]


def waypoint_mission(home_lat: float, home_lon: float, offsets_m: list[tuple[float, float]], alt_m: float = 10.0,
                     land: bool = True) -> list[MissionItem]:
    """Home slot, takeoff, one waypoint per (east, north) offset from home in metres, then land."""
    home = Home(home_lat, home_lon, 0.0)
    items = [MissionItem(0, MavCmd.NAV_WAYPOINT, Frame.GLOBAL, lat_deg=home_lat, lon_deg=home_lon),
             MissionItem(1, MavCmd.NAV_TAKEOFF, Frame.GLOBAL_RELATIVE_ALT_INT, alt_m=alt_m)]
    for east, north in offsets_m:
        wp = offset_home(home, east, north)
        items.append(MissionItem(len(items), MavCmd.NAV_WAYPOINT, Frame.GLOBAL_RELATIVE_ALT_INT,
                                 lat_deg=wp.lat_deg, lon_deg=wp.lon_deg, alt_m=alt_m))
    if land:
        items.append(MissionItem(len(items), MavCmd.NAV_LAND, Frame.GLOBAL_RELATIVE_ALT_INT))
    return items


class Gcs(VehicleClient):
    def __init__(self, port: int, sysid: int = 1, source_system: int = 255):
        super().__init__(f"udpin:127.0.0.1:{port}", sysid=sysid, source_system=source_system)


def take_off(gcs: Gcs, alt_m: float) -> None:
    """Arm, take off in GUIDED and wait for the vehicle to say it reached the altitude."""
    assert gcs.command(MavCmd.COMPONENT_ARM_DISARM, 1) == M.MAV_RESULT_ACCEPTED
    assert gcs.command(MavCmd.NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt_m) == M.MAV_RESULT_ACCEPTED
    assert gcs.recv("STATUSTEXT", 10.0, lambda m: "Takeoff complete" in m.text) is not None
