"""MAVLink 2 signing keys, shared by the ground station, the agent and the SITL (stdlib only).

A key file holds either 64 hex characters (the 32-byte secret itself) or a passphrase, whose SHA-256 is the
secret, as MAVProxy's `signing setup PASSPHRASE` derives it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path


class SigningKeyError(ValueError):
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
