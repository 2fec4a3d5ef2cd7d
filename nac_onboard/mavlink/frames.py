"""MAVLink frames found in raw bytes without decoding them: where each frame starts and ends, its message id and
source. Pure (no pymavlink), so readers can decode only the messages they need (the agent's link, log parsing)
and pass the rest on byte for byte. Frames are not CRC-checked here; whoever decodes one checks it.
"""

from __future__ import annotations

MAGIC_V1, MAGIC_V2 = 0xFE, 0xFD
_HEADER_V1, _HEADER_V2, _CRC, _SIGNATURE = 6, 10, 2, 13


def split_frames(data, start: int = 0) -> tuple[list[bytes], int, int]:
    """Whole frames in data[start:]; returns (frames, index of the first byte not consumed, bytes skipped as
    garbage). A frame cut off at the end is left unconsumed for the next read of a stream link."""
    frames: list[bytes] = []
    i, n, skipped = start, len(data), 0
    while i < n:
        magic = data[i]
        if magic == MAGIC_V2:
            if n - i < 3:
                break
            length = _HEADER_V2 + data[i + 1] + _CRC + (_SIGNATURE if data[i + 2] & 1 else 0)
        elif magic == MAGIC_V1:
            if n - i < 2:
                break
            length = _HEADER_V1 + data[i + 1] + _CRC
        else:
            v2, v1 = data.find(b"\xfd", i), data.find(b"\xfe", i)
            nxt = min((p for p in (v1, v2) if p >= 0), default=n)
            skipped += nxt - i
            i = nxt
            continue
        if n - i < length:
            break
        frames.append(bytes(data[i:i + length]))
        i += length
    return frames, i, skipped


def frame_msgid(frame: bytes) -> int:
    if frame[0] == MAGIC_V2:
        return frame[7] | frame[8] << 8 | frame[9] << 16
    return frame[5]


def frame_source(frame: bytes) -> tuple[int, int]:
    """(system id, component id) of the sender."""
    return (frame[5], frame[6]) if frame[0] == MAGIC_V2 else (frame[3], frame[4])
