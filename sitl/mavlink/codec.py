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

from nac_onboard.mavlink.frames import CRC, HEADER_V2, INCOMPAT_SIGNED, MAGIC_V2  # noqa: E402
from nac_onboard.mavlink.signing import SigningState, signature_block  # noqa: E402

try:  # pymavlink's own optional accelerator; the pure-Python CRC is the fallback
    from fastcrc.crc16 import mcrf4xx as _mcrf4xx
except ImportError:  # pragma: no cover
    _mcrf4xx = None


def _crc(data: bytes) -> int:
    if _mcrf4xx is not None:
        return _mcrf4xx(data, 0xFFFF)
    return x25crc(data).crc

__all__ = ["FrameEncoder", "mavlink", "new_parser", "parse_datagram"]



def new_parser(signing: SigningState | None = None) -> mavlink.MAVLink:
    """A parser that turns garbage into BAD_DATA messages instead of raising. With signing, unsigned or wrongly
    signed frames become BAD_DATA too (RADIO_STATUS excepted, as on ArduPilot: radios cannot sign), and the
    timestamps checked live in the shared state: a new parser does not forget them."""
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True
    if signing is not None:
        signing.install(parser)
        parser.signing.sign_outgoing = False
        parser.signing.allow_unsigned_callback = (
            lambda _mav, msgid: msgid == mavlink.MAVLINK_MSG_ID_RADIO_STATUS)
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


class ProtocolVersionMessage:
    """PROTOCOL_VERSION (300) as FrameEncoder.fields() reads a message class: the message is in MAVLink's
    common.xml but in no dialect pymavlink generates (its CRC extra, 217, is computed from that definition)."""

    id = 300
    crc_extra = 217
    unpacker = struct.Struct("<HHH8s8s")
    fieldnames = ordered_fieldnames = ["version", "min_version", "max_version", "spec_version_hash",
                                       "library_version_hash"]


class FrameEncoder:
    """Encodes frames for one source (sysid/compid) with its own sequence counter."""

    def __init__(self, sysid: int, compid: int = 1, signing: SigningState | None = None, link_id: int = 0):
        self.sysid = sysid
        self.compid = compid
        self.seq = 0
        self._mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        self._cache: dict[int, tuple[tuple, bytes]] = {}
        self.signing = signing  # timestamps follow the clock and never repeat, across restarts too
        self.link_id = link_id
        if signing is not None:
            self._mav.signing.secret_key = signing.key
            self._mav.signing.sign_outgoing = True
            self._mav.signing.link_id = link_id

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
        signed = self.signing is not None
        header = HEADER_V2.pack(MAGIC_V2, len(payload), INCOMPAT_SIGNED if signed else 0, 0, self.seq, self.sysid,
                              self.compid, layout.msgid & 0xFFFF, layout.msgid >> 16)
        self.seq = (self.seq + 1) & 0xFF
        body = header + payload
        frame = body + CRC.pack(_crc(body[1:] + layout.crc_extra))
        if signed:
            frame += signature_block(self.signing.key, frame, self.link_id, self.signing.next_timestamp())
        return frame

    def message(self, msg) -> bytes:
        """Encode any pymavlink message object (arrays, strings, extensions)."""
        self._mav.seq = self.seq
        if self.signing is not None:
            self._mav.signing.timestamp = self.signing.next_timestamp()
        frame = msg.pack(self._mav)
        self.seq = (self.seq + 1) & 0xFF
        return frame
