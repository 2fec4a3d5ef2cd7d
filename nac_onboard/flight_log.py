"""Flight logs: append-only JSON Lines and MAVLink `.tlog`, written so a crash loses at most the last record.

Each JSON record is one line `{"t_s": unix seconds, "kind": ..., ...}` handed to the kernel in a single write
(O_APPEND), so a killed process leaves whole lines and, at worst, one partial last line; `read_jsonl` skips that
line and says so. Kinds and their fields are defined in `nac_onboard.records.kinds`; a new file starts with a
`schema` record naming the schema version its records follow. A `.tlog` is what QGroundControl and pymavlink's
mavlogdump read: before each MAVLink frame, its receive time as an 8-byte big-endian count of microseconds since the
Unix epoch.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from nac_onboard.errors import BadInput
from nac_onboard.inputs import MAX_LOG_BYTES, read_bounded
from nac_onboard.mavlink.frames import TLOG_STAMP
from nac_onboard.records import READABLE_VERSIONS, SCHEMA_VERSION, Kind, kinds
from nac_onboard.records.schema import check

log = logging.getLogger(__name__)

# One encoder for every record: json.dumps with options builds a new encoder per call, a third of its cost.
_STRICT = json.JSONEncoder(separators=(",", ":"), allow_nan=False)
_LENIENT = json.JSONEncoder(separators=(",", ":"))


def finite_number(value) -> bool:
    """A JSON number that is finite (not a bool, a string, None, NaN or infinity)."""
    kind = type(value)
    if kind is float:  # the usual case first: a replay asks this a million times
        return value - value == 0.0
    if kind is int:
        return True
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def json_finite(value):
    """JSON has no NaN or infinity: an unknown number is written as null (logs, the state feed)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_finite(v) for v in value]
    return value


#: A full disk, a quota, a file-size limit: the log stops taking records, the program goes on (routing, peers,
#: the state feed and probes do not depend on the log), and the log resumes when it can, saying what was lost.
_FULL = frozenset({errno.ENOSPC, errno.EFBIG, errno.EDQUOT})
RETRY_S = 5.0


@dataclass
class Gap:
    """What a log could not write, from when, and why."""

    since_s: float
    error: str
    records: int = 0
    bytes: int = 0


class _AppendFile:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self._lock = threading.Lock()
        self.gap: Gap | None = None  # while records are being lost
        self._retry_at = 0.0

    def _write(self, data: bytes) -> None:
        with self._lock:
            if self._fd < 0:
                raise ValueError(f"{self.path} is closed")
            if self.gap is not None:
                if time.monotonic() < self._retry_at:
                    self.gap.records += 1
                    self.gap.bytes += len(data)
                    return
                data = self._resume_prefix() + data
            try:
                view = memoryview(data)
                while view:  # a regular file takes it whole; the loop covers a signal cutting a write short
                    view = view[os.write(self._fd, view):]
            except OSError as err:
                if err.errno not in _FULL:
                    raise
                self._lost(len(data), err)
                return
            if self.gap is not None:
                log.warning("%s: writing again after losing %d records (%d bytes)", self.path, self.gap.records,
                            self.gap.bytes)
                self.gap = None

    def _lost(self, nbytes: int, err: OSError) -> None:
        if self.gap is None:
            self.gap = Gap(time.time(), f"{errno.errorcode.get(err.errno, err.errno)}: {err.strerror}")
            log.warning("%s: cannot write (%s); records are dropped and counted until it can", self.path,
                        self.gap.error)
        self.gap.records += 1
        self.gap.bytes += nbytes
        self._retry_at = time.monotonic() + RETRY_S

    def _resume_prefix(self) -> bytes:
        """What goes before the first record after a gap (the gap record, for a JSON Lines log)."""
        return b""

    def sync(self) -> None:
        with self._lock:
            if self._fd >= 0:
                try:
                    os.fsync(self._fd)
                except OSError as err:
                    if err.errno not in _FULL:
                        raise

    def close(self) -> None:
        self.sync()
        with self._lock:
            if self._fd >= 0:
                os.close(self._fd)
                self._fd = -1

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class JsonlLog(_AppendFile):
    """One record per line, each with t_s and kind; thread-safe. After a full disk, the first record written is
    `log_gap` (records and bytes lost, from when, until when, why), on a line of its own even if the failed write
    left half a line behind."""

    def __init__(self, path: str | Path, t_s: float | None = None):
        super().__init__(path)
        if os.fstat(self._fd).st_size == 0:  # a new file (an agent restarted on its old log appends to it)
            self.write(kinds.SCHEMA, t_s, schema_version=SCHEMA_VERSION, file=self.path.name)
        elif self._ends_mid_line():  # its writer was killed mid-record: that part stays a (damaged) line of its own
            self._write(b"\n")

    def _resume_prefix(self) -> bytes:
        g = self.gap
        record = {"t_s": time.time(), "kind": kinds.LOG_GAP.name, "since_s": g.since_s, "records_lost": g.records,
                  "bytes_lost": g.bytes, "error": g.error}
        return (("\n" if self._ends_mid_line() else "") + _STRICT.encode(record) + "\n").encode()

    def _ends_mid_line(self) -> bool:
        """Whether the failed write left part of a record behind (it is then a damaged line of its own)."""
        try:
            with open(self.path, "rb") as f:
                f.seek(0, os.SEEK_END)
                if f.tell() == 0:
                    return False
                f.seek(-1, os.SEEK_END)
                return f.read(1) != b"\n"
        except OSError:
            return True

    def write(self, kind: Kind, t_s: float | None = None, **fields) -> dict:
        check(kind, fields)
        record = {"t_s": time.time() if t_s is None else t_s, "kind": kind.name, **fields}
        try:
            line = _STRICT.encode(record)
        except ValueError:  # a NaN or infinity somewhere: the slower walk that writes them as null
            line = _LENIENT.encode(json_finite(record))
        self._write((line + "\n").encode())
        return record


class TlogWriter(_AppendFile):
    """MAVLink frames with their time, the `.tlog` layout. `now_s` gives the stamps (unix seconds; default the wall
    clock): a sped-up SITL run's agent stamps on the run's clock, so that MAVExplorer and mavflightmodes.py read
    its flight's durations in simulated seconds."""

    def __init__(self, path: str | Path, now_s=time.time):
        super().__init__(path)
        self.now_s = now_s

    def write(self, frame: bytes, t_s: float | None = None) -> None:
        self.write_many([frame], t_s)

    def write_many(self, frames: list[bytes], t_s: float | None = None) -> None:
        """Frames that arrived together, in one write."""
        if frames:
            stamp = TLOG_STAMP.pack(int((self.now_s() if t_s is None else t_s) * 1e6))
            self._write(b"".join(stamp + bytes(frame) for frame in frames))


@dataclass
class LogRead:
    """What a JSON Lines log held: its records and the lines that could not be read, each named."""

    path: Path
    records: list[dict] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    truncated_tail: bool = False  # the last line was cut short (the writer stopped mid-record)
    schema_version: int = 0  # from the file's schema record; 0: a file written before versions

    def of_kind(self, *wanted: Kind | str) -> list[dict]:
        names = {getattr(k, "name", k) for k in wanted}
        return [r for r in self.records if r["kind"] in names]


class RecordsVersionError(BadInput):
    """A file written by a newer NAC, whose records this one cannot read."""


def read_jsonl(path: str | Path) -> LogRead:
    """Read a log written by JsonlLog. Bad lines are skipped and described in .problems, never raised; a file of a
    schema version this code does not read raises RecordsVersionError naming the version. The schema record is
    taken out of .records; kinds and fields this code does not know are kept."""
    path = Path(path)
    out = LogRead(path)
    data = read_bounded(path, "log", MAX_LOG_BYTES)  # a regular file within the limit: BadInput names it otherwise
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
        if record["kind"] == kinds.SCHEMA.name:
            out.schema_version = _readable_version(path, number, record.get("schema_version"))
            continue
        out.records.append(record)
    return out


def _readable_version(path: Path, line: int, version) -> int:
    if version in READABLE_VERSIONS and not isinstance(version, bool):
        return version
    raise RecordsVersionError(f"{path}: line {line}: records of schema version {version!r}; this NAC reads versions "
                              f"{', '.join(map(str, READABLE_VERSIONS))}: read it with the NAC that wrote it (or a "
                              "newer one)")
