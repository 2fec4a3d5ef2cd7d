"""The SITL's one door to pymavlink: the dialect, a parser per channel and a fast MAVLink 2 frame encoder.

High-rate telemetry is encoded here straight from field values (struct + CRC), reusing the packed payload when
a message's values have not changed since it was last sent; pymavlink packs everything else.
"""

from __future__ import annotations

import os
import struct

os.environ.setdefault("MAVLINK20", "1")

from pymavlink.dialects.v20 import all as mavlink  # noqa: E402
from pymavlink.generator.mavcrc import x25crc  # noqa: E402

try:  # pymavlink's own optional accelerator; the pure-Python CRC is the fallback
    from fastcrc.crc16 import mcrf4xx as _mcrf4xx
except ImportError:  # pragma: no cover
    _mcrf4xx = None


def _crc(data: bytes) -> int:
    if _mcrf4xx is not None:
        return _mcrf4xx(data, 0xFFFF)
    return x25crc(data).crc

__all__ = ["FrameEncoder", "mavlink", "new_parser", "parse_datagram"]

_HEADER = struct.Struct("<BBBBBBBHB")
_CRC = struct.Struct("<H")


def new_parser() -> mavlink.MAVLink:
    """A parser that turns garbage into BAD_DATA messages instead of raising."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    return parser


def parse_datagram(parser: mavlink.MAVLink, data: bytes) -> list:
    """Parse one UDP datagram. Frames never span datagrams, so a partial frame left over (garbage that looked
    like a header) is discarded instead of swallowing the start of the next datagram."""
    messages = parser.parse_buffer(data) or []
    if parser.buf_len():
        parser.buf = bytearray()
        parser.buf_index = 0
        parser.expected_length = mavlink.HEADER_LEN_V1 + 2
    return messages


class _Layout:
    __slots__ = ("msgid", "crc_extra", "packer", "order")

    def __init__(self, cls):
        self.msgid = cls.id
        self.crc_extra = bytes((cls.crc_extra,))
        self.packer = cls.unpacker
        order = [cls.fieldnames.index(name) for name in cls.ordered_fieldnames]
        self.order = None if order == sorted(order) else order


_LAYOUTS: dict[type, _Layout] = {}


def _layout(cls) -> _Layout:
    layout = _LAYOUTS.get(cls)
    if layout is None:
        layout = _LAYOUTS[cls] = _Layout(cls)
    return layout


class FrameEncoder:
    """Encodes frames for one source (sysid/compid) with its own sequence counter."""

    def __init__(self, sysid: int, compid: int = 1):
        self.sysid = sysid
        self.compid = compid
        self.seq = 0
        self._mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._cache: dict[int, tuple[tuple, bytes]] = {}

    def fields(self, cls, *values) -> bytes:
        """Encode a message given its field values in declaration order (scalar-only messages)."""
        layout = _layout(cls)
        cached = self._cache.get(layout.msgid)
        if cached is not None and cached[0] == values:
            payload = cached[1]
        else:
            ordered = values if layout.order is None else [values[k] for k in layout.order]
            payload = layout.packer.pack(*ordered)
            end = len(payload)
            while end > 1 and payload[end - 1] == 0:  # MAVLink 2 trims trailing zeros
                end -= 1
            payload = payload[:end]
            self._cache[layout.msgid] = (values, payload)
        header = _HEADER.pack(0xFD, len(payload), 0, 0, self.seq, self.sysid, self.compid,
                              layout.msgid & 0xFFFF, layout.msgid >> 16)
        self.seq = (self.seq + 1) & 0xFF
        body = header + payload
        return body + _CRC.pack(_crc(body[1:] + layout.crc_extra))

    def message(self, msg) -> bytes:
        """Encode any pymavlink message object (arrays, strings, extensions)."""
        self._mav.seq = self.seq
        frame = msg.pack(self._mav)
        self.seq = (self.seq + 1) & 0xFF
        return frame
