"""Routing endpoints of the agent: MAVLink links whose frames are relayed byte for byte between the autopilot and
local tools (MAVProxy, QGroundControl, scripts). Who may command the vehicle through them is decided here:

  udpout:HOST:PORT   we send to HOST:PORT from a socket bound to loopback (or to the address that reaches HOST) and
                     connected to it: the kernel delivers only that peer's datagrams
  udpin:ADDR:PORT    we listen on ADDR:PORT and answer the first peer that speaks; datagrams from anyone else are
                     dropped and counted (`allow` names more peers that may speak)
  tcp:HOST:PORT, serial:DEVICE:BAUD   one connection, one peer by construction
A read-only endpoint (`watch` in the config) gets the telemetry and nothing it sends is forwarded.
"""

from __future__ import annotations

import socket

from nac_onboard.address import is_loopback, parse_host_port
from nac_onboard.mavlink.client import LinkError, mavutil_device
from nac_onboard.mavlink.dialect import mavutil
from nac_onboard.mavlink.frames import split_frames

MAX_DATAGRAM_BYTES = 65535


class RawEndpoint:
    def __init__(self, uri: str, read_only: bool = False, allow: tuple[tuple[str, int], ...] = ()):
        self.uri, self.read_only = uri, read_only
        self.allow = set(allow)
        self.peer: tuple[str, int] | None = None  # UDP: the one sender we answer
        self.dropped_frames = 0  # from senders not allowed, or sent to a read-only endpoint
        self.last_dropped_from: tuple[str, int] | None = None
        self.sock: socket.socket | None = None
        self.conn = None
        self._buffer = memoryview(bytearray(MAX_DATAGRAM_BYTES))  # one receive buffer: a refused datagram costs
        # no allocation (recvfrom(65535) allocates and shrinks 64 KB per datagram: most of a flood's cost)
        scheme, _, rest = uri.partition(":")
        self.connected = scheme == "udpout"  # the kernel keeps to the one peer
        device, options = mavutil_device(uri)  # BadInput for a malformed URI
        try:
            if scheme == "udpout":
                host, port = parse_host_port(rest, f"routing endpoint {uri}")
                self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self.sock.bind(("127.0.0.1" if is_loopback(host) else "0.0.0.0", 0))
                self.sock.connect((host, port))
                self.peer = (host, port)
            elif scheme == "udpin":
                host, port = parse_host_port(rest, f"routing endpoint {uri}", allow_port_zero=True)
                self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self.sock.bind((host, port))
            else:
                self.conn = mavutil.mavlink_connection(device, **options)
                self.conn.mav.robust_parsing = True
        except OSError as err:
            if self.sock is not None:
                self.sock.close()
            raise LinkError(f"cannot open routing endpoint {uri}: {err.strerror or err}") from None
        if self.sock is not None:
            self.sock.setblocking(False)

    @property
    def last_dropped_sender(self) -> str:
        """HOST:PORT of the last sender refused ("" if none), for the log."""
        return f"{self.last_dropped_from[0]}:{self.last_dropped_from[1]}" if self.last_dropped_from else ""

    def fileno(self) -> int:
        if self.sock is not None:
            return self.sock.fileno()
        return self.conn.fd if getattr(self.conn, "fd", None) is not None else self.conn.port.fileno()

    def read_frames(self) -> list[bytes]:
        """Frames to forward to the autopilot: none from a read-only endpoint or from a sender not allowed."""
        frames = self._read_sock() if self.sock is not None else self._read_conn()
        if self.read_only and frames:
            self.dropped_frames += len(frames)
            return []
        return frames

    def _read_sock(self) -> list[bytes]:
        frames: list[bytes] = []
        buffer, receive = self._buffer, self.sock.recvfrom_into
        for _ in range(256):  # bounded: a flood cannot hold the agent's loop (10 ms of a 25,000/s flood)
            try:
                size, sender = receive(buffer)
            except (BlockingIOError, InterruptedError, ConnectionRefusedError):
                return frames
            except OSError:
                return frames
            if self.peer is None and (not self.allow or sender in self.allow):
                self.peer = sender  # udpin: the first allowed peer that speaks is the one we answer
            if sender != self.peer and sender not in self.allow:
                self.dropped_frames += 1
                self.last_dropped_from = sender
                continue
            frames.extend(split_frames(bytes(buffer[:size]))[0])
        return frames

    def _read_conn(self) -> list[bytes]:
        frames = []
        while (msg := self.conn.recv_msg()) is not None:
            if msg.get_type() != "BAD_DATA":
                frames.append(bytes(msg.get_msgbuf()))
        return frames

    def write(self, frame: bytes) -> bool:
        try:
            if self.sock is None:
                self.conn.write(frame)
            elif self.connected:
                self.sock.send(frame)
            elif self.peer is None:
                return False  # udpin: nobody has spoken yet
            else:
                self.sock.sendto(frame, self.peer)
        except OSError:
            return False  # nobody listening yet (udpout before the tool starts): the frame is simply not routed
        return True

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        if self.conn is not None:
            self.conn.close()
