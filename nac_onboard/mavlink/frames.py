"""MAVLink frames found in raw bytes without decoding them: where each frame starts and ends, its message id and
source. Pure (no pymavlink), so readers can decode only the messages they need (the agent's link, log parsing)
and pass the rest on byte for byte. Frames are not CRC-checked here; whoever decodes one checks it.
"""

from __future__ import annotations

import struct

MAGIC_V1, MAGIC_V2 = 0xFE, 0xFD
INCOMPAT_SIGNED = 0x01  # MAVLink 2 incompat_flags: a signature block follows the CRC
#: MAVLink 2 header: magic, payload length, incompat flags, compat flags, sequence, sysid, compid, msgid (24 bits)
HEADER_V2 = struct.Struct("<BBBBBBBHB")
CRC = struct.Struct("<H")
TLOG_STAMP = struct.Struct(">Q")  # a .tlog record: this µs unix timestamp, then one frame
_HEADER_V1, _HEADER_V2, _CRC, _SIGNATURE = 6, HEADER_V2.size, CRC.size, 13


def frame_length(data, i: int, n: int) -> int | None:
    """Bytes of the frame starting at data[i] (header, payload, CRC, signature); None when no frame starts there
    or its header is not all in data[:n] yet."""
    magic = data[i]
    if magic == MAGIC_V2:
        if n - i < 3:
            return None
        return _HEADER_V2 + data[i + 1] + _CRC + (_SIGNATURE if data[i + 2] & INCOMPAT_SIGNED else 0)
    if magic == MAGIC_V1:
        if n - i < 2:
            return None
        return _HEADER_V1 + data[i + 1] + _CRC
    return None


def msgid_at(data, i: int) -> int:
    """Message id of the frame starting at data[i] (its header must be there)."""
    if data[i] == MAGIC_V2:
        return data[i + 7] | data[i + 8] << 8 | data[i + 9] << 16
    return data[i + 5]


def split_frames(data, start: int = 0) -> tuple[list[bytes], int, int]:
    """Whole frames in data[start:]; returns (frames, index of the first byte not consumed, bytes skipped as
    garbage). A frame cut off at the end is left unconsumed for the next read of a stream link."""
    frames: list[bytes] = []
    i, n, skipped = start, len(data), 0
    while i < n:
        if data[i] not in (MAGIC_V1, MAGIC_V2):
            v2, v1 = data.find(b"\xfd", i), data.find(b"\xfe", i)
            nxt = min((p for p in (v1, v2) if p >= 0), default=n)
            skipped += nxt - i
            i = nxt
            continue
        length = frame_length(data, i, n)
        if length is None or n - i < length:
            break
        frames.append(bytes(data[i:i + length]))
        i += length
    return frames, i, skipped


def frame_msgid(frame: bytes) -> int:
    return msgid_at(frame, 0)


def frame_source(frame: bytes) -> tuple[int, int]:
    """(system id, component id) of the sender."""
    return (frame[5], frame[6]) if frame[0] == MAGIC_V2 else (frame[3], frame[4])
