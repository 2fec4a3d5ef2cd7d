"""Flight logs: append-only JSON Lines and MAVLink `.tlog`, written so a crash loses at most the last record.

Each JSON record is one line `{"t_s": unix seconds, "kind": ..., ...}` handed to the kernel in a single write
(O_APPEND), so a killed process leaves whole lines and, at worst, one partial last line; `read_jsonl` skips that
line and says so. A `.tlog` is what QGroundControl and pymavlink's mavlogdump read: before each MAVLink frame, its
receive time as an 8-byte big-endian count of microseconds since the Unix epoch.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from nac_onboard.mavlink.frames import TLOG_STAMP

# One encoder for every record: json.dumps with options builds a new encoder per call, a third of its cost.
_STRICT = json.JSONEncoder(separators=(",", ":"), allow_nan=False)
_LENIENT = json.JSONEncoder(separators=(",", ":"))


def _finite(value):
    """JSON has no NaN or infinity: an unknown number is written as null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


class _AppendFile:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self._lock = threading.Lock()

    def _write(self, data: bytes) -> None:
        with self._lock:
            if self._fd < 0:
                raise ValueError(f"{self.path} is closed")
            view = memoryview(data)
            while view:  # a regular file takes it whole; the loop covers a signal cutting a write short
                view = view[os.write(self._fd, view):]

    def sync(self) -> None:
        with self._lock:
            if self._fd >= 0:
                os.fsync(self._fd)

    def close(self) -> None:
        with self._lock:
            if self._fd >= 0:
                os.fsync(self._fd)
                os.close(self._fd)
                self._fd = -1

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class JsonlLog(_AppendFile):
    """One record per line, each with t_s and kind; thread-safe."""

    def write(self, kind: str, t_s: float | None = None, **fields) -> dict:
        record = {"t_s": time.time() if t_s is None else t_s, "kind": kind, **fields}
        try:
            line = _STRICT.encode(record)
        except ValueError:  # a NaN or infinity somewhere: the slower walk that writes them as null
            line = _LENIENT.encode(_finite(record))
        self._write((line + "\n").encode())
        return record


class TlogWriter(_AppendFile):
    """MAVLink frames with their time, the `.tlog` layout."""

    def write(self, frame: bytes, t_s: float | None = None) -> None:
        self.write_many([frame], t_s)

    def write_many(self, frames: list[bytes], t_s: float | None = None) -> None:
        """Frames that arrived together, in one write."""
        if frames:
            stamp = TLOG_STAMP.pack(int((time.time() if t_s is None else t_s) * 1e6))
            self._write(b"".join(stamp + bytes(frame) for frame in frames))


@dataclass
class LogRead:
    """What a JSON Lines log held: its records and the lines that could not be read, each named."""

    path: Path
    records: list[dict] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    truncated_tail: bool = False  # the last line was cut short (the writer stopped mid-record)

    def of_kind(self, *kinds: str) -> list[dict]:
        return [r for r in self.records if r["kind"] in kinds]


def read_jsonl(path: str | Path) -> LogRead:
    """Read a log written by JsonlLog. Bad lines are skipped and described in .problems, never raised."""
    path = Path(path)
    out = LogRead(path)
    data = path.read_bytes()
    lines = data.split(b"\n")
    complete = data.endswith(b"\n") or not data
    if complete:
        lines.pop()  # the empty string after the final newline
    for number, raw in enumerate(lines, start=1):
        last = number == len(lines)
        try:
            record = json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            record = None
        if last and not complete:
            out.truncated_tail = True
            out.problems.append(f"{path}: line {number}: last record is incomplete (the writer stopped mid-record); "
                                "skipped")
            continue
        if not isinstance(record, dict) or not isinstance(record.get("kind"), str) \
                or not isinstance(record.get("t_s"), (int, float)):
            out.problems.append(f"{path}: line {number}: not a log record (expected a JSON object with t_s and "
                                "kind); skipped")
            continue
        out.records.append(record)
    return out
