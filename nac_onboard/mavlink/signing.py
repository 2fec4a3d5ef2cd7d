"""MAVLink 2 signing, shared by the ground station, the agent and the SITL (stdlib only): keys, timestamps and
the signature block.

A key file holds either 64 hex characters (the 32-byte secret itself) or a passphrase, whose SHA-256 is the
secret, as MAVProxy's `signing setup PASSPHRASE` derives it.
"""

from __future__ import annotations

import hashlib
import json
import os
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
    from nac_onboard.inputs import read_bounded_text

    path = Path(path)
    # a regular file of at most 64 KiB, read without blocking: a FIFO or /dev/zero is refused, not waited on
    text = read_bounded_text(path, "signing key file", 64 * 1024, SigningKeyError).strip()
    if not text:
        raise SigningKeyError(f"signing key file {path} is empty: expected 64 hex characters or a passphrase")
    if len(text) == 64:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    return hashlib.sha256(text.encode()).digest()


MAX_AHEAD = 60 * 100_000  # a signed frame dated more than a minute ahead of us is refused (10 µs units)
NEW_STREAM_BEHIND = 60 * 100_000  # a stream we never heard may start at most a minute behind us (pymavlink's rule)
SAVE_EVERY_S = 1.0


class SigningState:
    """The timestamps MAVLink 2 signing depends on, for one key on this machine: the last one we used and the last
    one accepted from each stream (link id, system, component). Kept in a file beside the key, so a restart neither
    accepts again frames captured before it nor reuses timestamps.

    Incoming frames are checked as the signing spec asks and pymavlink does not: the signature first, before any
    state changes (pymavlink stores a frame's timestamp before checking it, so one forged frame dated far ahead
    locks the real sender out), then the timestamp, which may not lie more than MAX_AHEAD ahead of ours.
    """

    def __init__(self, key: bytes, path: str | Path | None = None):
        self.key = key
        self.path = Path(path) if path else None
        self.own = initial_timestamp()
        self.streams: dict[tuple[int, int, int], int] = {}
        self.refused = {"signature": 0, "ahead": 0, "replayed": 0}
        self._saved_s = 0.0
        self._dirty = False
        if self.path is not None and self.path.exists():
            self._load()

    def _load(self) -> None:
        try:
            saved = json.loads(self.path.read_text())
            self.own = max(self.own, int(saved["own"]) + 1)
            self.streams = {tuple(int(x) for x in key.split(",")): int(ts) for key, ts in saved["streams"].items()}
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            raise SigningKeyError(f"signing state {self.path}: unreadable ({err}); delete it only if no frame "
                                  "signed before it was written can be replayed") from None

    def next_timestamp(self) -> int:
        """For the next frame we sign: after every one used, and not behind the clock."""
        self.own = max(self.own + 1, initial_timestamp())
        self._dirty = True
        return self.own

    def accept(self, msgbuf, src_system: int, src_component: int) -> bool:
        """pymavlink's check_signature, in the order the spec asks (install() puts it on a parser)."""
        if hashlib.sha256(self.key + bytes(msgbuf[:-6])).digest()[:6] != bytes(msgbuf[-6:]):
            self.refused["signature"] += 1
            return False
        low, high = struct.unpack("<IH", bytes(msgbuf[-12:-6]))
        timestamp = low + (high << 32)
        now = max(self.own, initial_timestamp())
        if timestamp > now + MAX_AHEAD:
            self.refused["ahead"] += 1
            return False
        stream = (msgbuf[-13], src_system, src_component)
        last = self.streams.get(stream)
        if (last is not None and timestamp <= last) or (last is None and timestamp + NEW_STREAM_BEHIND < now):
            self.refused["replayed"] += 1
            return False
        self.streams[stream] = timestamp
        self.own = max(self.own, timestamp)
        self._dirty = True
        self.save()
        return True

    def install(self, mav) -> None:
        """Make a pymavlink MAVLink object check incoming signatures with this state."""
        mav.signing.secret_key = self.key
        mav.signing.timestamp = self.own
        mav.check_signature = self.accept

    def save(self, force: bool = False) -> None:
        """Write the state (atomically) at most every SAVE_EVERY_S, or now when forced (at exit)."""
        if self.path is None or not self._dirty:
            return
        now_s = time.monotonic()
        if not force and now_s - self._saved_s < SAVE_EVERY_S:
            return
        body = {"own": self.own, "streams": {",".join(map(str, k)): v for k, v in self.streams.items()}}
        partial = self.path.with_name(self.path.name + ".partial")
        try:
            partial.write_text(json.dumps(body))
            os.replace(partial, self.path)
        except OSError:
            return  # a read-only or full disk: the in-memory state still protects this run
        self._saved_s, self._dirty = now_s, False


def state_path(key_file: str | Path) -> Path:
    """Where the signing state of a key file lives: beside it."""
    key_file = Path(key_file)
    return key_file.with_name(key_file.name + ".timestamps")
