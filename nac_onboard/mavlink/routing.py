"""Routing endpoints of the agent: MAVLink links whose frames are relayed byte for byte between the autopilot
and local tools (MAVProxy, QGroundControl, scripts)."""

from __future__ import annotations

from nac_onboard.mavlink.client import LinkError, mavutil_device
from nac_onboard.mavlink.dialect import mavutil


class RawEndpoint:
    """A MAVLink endpoint whose frames are relayed byte for byte (the agent's routing to MAVProxy and tools)."""

    def __init__(self, uri: str):
        self.uri = uri
        device, options = mavutil_device(uri)
        try:
            self.conn = mavutil.mavlink_connection(device, **options)
        except OSError as err:
            raise LinkError(f"cannot open routing endpoint {uri}: {err.strerror or err}") from None
        self.conn.mav.robust_parsing = True

    def fileno(self) -> int:
        return self.conn.fd if getattr(self.conn, "fd", None) is not None else self.conn.port.fileno()

    def read_frames(self) -> list[bytes]:
        frames = []
        while (msg := self.conn.recv_msg()) is not None:
            if msg.get_type() != "BAD_DATA":
                frames.append(bytes(msg.get_msgbuf()))
        return frames

    def write(self, frame: bytes) -> bool:
        try:
            self.conn.write(frame)
        except OSError:
            return False  # nobody listening yet (udpout before the tool starts): the frame is simply not routed
        return True

    def close(self) -> None:
        self.conn.close()
