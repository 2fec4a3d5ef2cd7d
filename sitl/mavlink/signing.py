"""MAVLink 2 signature block for the SITL's own fast encoder (stdlib only). Keys: nac_onboard.signing."""

from __future__ import annotations

import hashlib
import struct
import time

SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01, the origin of MAVLink signing timestamps
INCOMPAT_SIGNED = 0x01


def initial_timestamp() -> int:
    """Signing timestamps count 10 µs units since 2015-01-01 and must only increase."""
    return int((max(time.time(), SIGNING_EPOCH_UNIX_S) - SIGNING_EPOCH_UNIX_S) * 100_000)


def signature_block(key: bytes, frame: bytes, link_id: int, timestamp: int) -> bytes:
    """The 13 bytes after a signed frame's CRC: link id, 48-bit timestamp, 48-bit SHA-256 signature."""
    stamp = struct.pack("<BQ", link_id, timestamp)[:7]
    return stamp + hashlib.sha256(key + frame + stamp).digest()[:6]
