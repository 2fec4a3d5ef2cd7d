"""MAVLink 2 signing, shared by the ground station, the agent and the SITL (stdlib only): keys, timestamps and
the signature block.

A key file holds either 64 hex characters (the 32-byte secret itself) or a passphrase, whose SHA-256 is the
secret, as MAVProxy's `signing setup PASSPHRASE` derives it.
"""

from __future__ import annotations

import hashlib
import struct
import time
from pathlib import Path

from nac_onboard.errors import BadInput

SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01, the origin of MAVLink signing timestamps


def initial_timestamp() -> int:
    """Signing timestamps count 10 µs units since 2015-01-01 and must only increase."""
    return int((max(time.time(), SIGNING_EPOCH_UNIX_S) - SIGNING_EPOCH_UNIX_S) * 100_000)


def signature_block(key: bytes, frame: bytes, link_id: int, timestamp: int) -> bytes:
    """The 13 bytes after a signed frame's CRC: link id, 48-bit timestamp, 48-bit SHA-256 signature."""
    stamp = struct.pack("<BQ", link_id, timestamp)[:7]
    return stamp + hashlib.sha256(key + frame + stamp).digest()[:6]


class SigningKeyError(BadInput):
    pass


def load_signing_key(path: str | Path) -> bytes:
    path = Path(path)
    try:
        text = path.read_text().strip()
    except OSError as err:
        raise SigningKeyError(f"cannot read signing key file {path}: {err.strerror}") from None
    except UnicodeDecodeError:
        raise SigningKeyError(f"signing key file {path}: expected 64 hex characters or a passphrase") from None
    if not text:
        raise SigningKeyError(f"signing key file {path} is empty: expected 64 hex characters or a passphrase")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return hashlib.sha256(text.encode()).digest()
