"""Positions from autopilot logs: MAVLink `.tlog`, ArduPilot DataFlash `.bin`, PX4 `.ulg`.

The one module in `ground/` that imports pymavlink (and pyulog). A `.tlog` is read without pymavlink's
byte-by-byte parser: records are walked by their length fields and only the wanted message types are decoded
(CRC-checked by pymavlink), which is what makes long flights quick to read. Damage is counted, never raised:
bytes that are not a record are skipped up to the next plausible one, frames failing their CRC are dropped.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from ground.logs.dataflash import read_positions_fast  # noqa: E402
from nac_onboard.errors import BadInput
from nac_onboard.inputs import MAX_AUTOPILOT_LOG_BYTES, check_regular_file, read_bounded
from nac_onboard.mavlink.frames import TLOG_STAMP, frame_length, msgid_at  # noqa: E402

STAMP_BYTES = TLOG_STAMP.size

_PLAUSIBLE_GAP_US = 86_400 * 10**6  # a record more than a day from its neighbour is damage, not a pause


class FlightLogError(BadInput):
    """A log that cannot be read at all (not a damaged one: damage is counted)."""


@dataclass
class TlogRead:
    path: Path
    messages: list = field(default_factory=list)  # (t_s, decoded pymavlink message), in file order
    frames: int = 0  # whole records seen, of every type
    skipped_bytes: int = 0  # bytes that were not a record, skipped while resynchronising
    bad_crc: int = 0  # wanted frames that failed their checksum
    truncated_tail: bool = False

    @property
    def problems(self) -> list[str]:
        out = []
        if self.skipped_bytes:
            out.append(f"{self.path}: {self.skipped_bytes} corrupt bytes skipped")
        if self.bad_crc:
            out.append(f"{self.path}: {self.bad_crc} messages with a bad checksum skipped")
        if self.truncated_tail:
            out.append(f"{self.path}: the last record is cut short (the writer stopped mid-record); skipped")
        return out


def message_ids(names) -> set[int]:
    ids = set()
    for name in names:
        msgid = getattr(mavlink, f"MAVLINK_MSG_ID_{name}", None)
        if msgid is None:
            raise FlightLogError(f"unknown MAVLink message {name!r}")
        ids.add(msgid)
    return ids


def _record_length(data: bytes, i: int, n: int) -> int | None:
    """Length of the tlog record at i (stamp + frame), or None when no frame starts at i + 8."""
    if i + 10 > n:
        return None
    length = frame_length(data, i + STAMP_BYTES, n)
    return None if length is None else STAMP_BYTES + length


def _resync(data: bytes, i: int, n: int, last_us: int | None) -> int:
    """The next offset after i where a record starts and is followed by another (or the end of the file)."""
    for j in range(i + 1, n - 9):
        length = _record_length(data, j, n)
        if length is None or j + length > n:
            continue
        if last_us is not None and abs(TLOG_STAMP.unpack_from(data, j)[0] - last_us) > _PLAUSIBLE_GAP_US:
            continue
        if j + length == n or _record_length(data, j + length, n) is not None:
            return j
    return n


def read_tlog(path: str | Path, wanted=("GLOBAL_POSITION_INT",)) -> TlogRead:
    """Decode the wanted message types of a `.tlog` (8-byte big-endian µs stamp before each frame)."""
    path = Path(path)
    out = TlogRead(path)
    data = read_bounded(path, "autopilot log", MAX_AUTOPILOT_LOG_BYTES, FlightLogError)
    wanted_ids = message_ids(wanted)
    decoder = mavlink.MAVLink(None)
    decoder.robust_parsing = True
    unpack_stamp = TLOG_STAMP.unpack_from
    i, n, last_us = 0, len(data), None
    while i < n:
        if n - i < 18:  # shorter than any whole record (the smallest frames are HEARTBEATs)
            out.truncated_tail = True
            break
        length = frame_length(data, i + STAMP_BYTES, n)
        if length is None:
            j = _resync(data, i, n, last_us)
            out.skipped_bytes += j - i
            i = j
            continue
        length += STAMP_BYTES
        msgid = msgid_at(data, i + STAMP_BYTES)
        if i + length > n:
            out.truncated_tail = True
            break
        out.frames += 1
        if msgid in wanted_ids:
            stamp_us = unpack_stamp(data, i)[0]
            try:
                msg = decoder.decode(bytearray(data[i + 8:i + length]))
            except mavlink.MAVError:
                out.bad_crc += 1
            else:
                last_us = stamp_us
                out.messages.append((stamp_us / 1e6, msg))
        i += length
    return out


def tlog_positions(path: str | Path, vehicle: str | None = None) -> tuple[list[dict], list[str]]:
    """GLOBAL_POSITION_INT rows of a `.tlog` (one vehicle per sysid when `vehicle` is not given)."""
    read = read_tlog(path)
    sysids = {msg.get_srcSystem() for _, msg in read.messages}
    rows = [{"vehicle": vehicle if vehicle and len(sysids) == 1 else f"{vehicle or ''}sysid{msg.get_srcSystem()}",
             "source": "tlog", "t_s": t_s, "time_base": "unix",
             "time_boot_ms": msg.time_boot_ms, "lat_deg": msg.lat / 1e7, "lon_deg": msg.lon / 1e7,
             "alt_m": msg.alt / 1000, "rel_alt_m": msg.relative_alt / 1000}
            for t_s, msg in read.messages]
    rows, no_fix = with_fix(rows, path)
    return rows, read.problems + no_fix


UNIX_TIME_AFTER_S = 1e9  # 2001: a smaller time is seconds since boot, not a date


def with_fix(rows: list[dict], path: str | Path) -> tuple[list[dict], list[str]]:
    """Rows with a position: an autopilot logs latitude = longitude = 0 (or NaN) before its GPS has a fix, and
    such a row would put the vehicle off the coast of Africa and the map's origin with it."""
    kept = [r for r in rows if r["lat_deg"] == r["lat_deg"] and r["lon_deg"] == r["lon_deg"]  # NaN is not kept
            and not (r["lat_deg"] == 0.0 and r["lon_deg"] == 0.0)]
    dropped = len(rows) - len(kept)
    return kept, [f"{path}: {dropped} of {len(rows)} position samples without a fix (latitude = longitude = 0) "
                  f"dropped"] if dropped else []


CHATTER_LINES = 5  # of what a reference reader printed, reported verbatim; the rest counted


@contextlib.contextmanager
def _reference_reader(path: Path, problems: list[str]):
    """pymavlink and pyulog print what they find wrong (to stdout or stderr) instead of raising: it goes into the
    report's problems, not onto the CLI's output."""
    printed = io.StringIO()
    with tempfile.TemporaryFile() as native, _native_output_to(native), contextlib.redirect_stdout(printed), \
            contextlib.redirect_stderr(printed):
        yield
        native.seek(0)
        printed.write(native.read().decode(errors="replace"))
    lines = list(dict.fromkeys(line.strip() for line in printed.getvalue().splitlines() if line.strip()))
    problems += [f"{path}: {line}" for line in lines[:CHATTER_LINES]]
    if len(lines) > CHATTER_LINES:
        problems.append(f"{path}: {len(lines) - CHATTER_LINES} more such messages from the reader")


@contextlib.contextmanager
def _native_output_to(file):
    """File descriptors 1 and 2 into `file` for a while: pymavlink's compiled log indexer writes to them directly."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        os.dup2(file.fileno(), 1)
        os.dup2(file.fileno(), 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


def dataflash_positions(path: str | Path, vehicle: str) -> tuple[list[dict], list[str]]:
    """POS rows of an ArduPilot DataFlash `.bin` (GPS rows when it has no POS; logs from before 2015 stamp them
    with TimeMS, later ones TimeUS), on pymavlink's clock: unix time from the GPS when the log has it, else
    seconds since boot (then said, and the rows' time_base is "boot"). Modern logs are walked by record length
    (ground.logs.dataflash); the rest go through pymavlink's DFReader."""
    path = Path(path)
    fast = read_positions_fast(read_bounded(path, "autopilot log", MAX_AUTOPILOT_LOG_BYTES, FlightLogError))
    if fast is None:
        return _dataflash_positions_dfreader(path, vehicle)
    pos, gps = fast.columns.get("POS"), fast.columns.get("GPS")
    columns = pos if pos is not None and len(pos["TimeUS"]) else gps
    rows = []
    if columns:
        time_us = columns["TimeUS"]
        rel_alt = columns["RelHomeAlt"].tolist() if "RelHomeAlt" in columns else [None] * len(time_us)
        rows = [{"vehicle": vehicle, "source": "dataflash", "t_s": t_s, "time_boot_ms": boot_ms, "lat_deg": lat,
                 "lon_deg": lon, "alt_m": alt, "rel_alt_m": rel}
                for t_s, boot_ms, lat, lon, alt, rel in zip(
                    (fast.timebase_s + time_us * 0.000001).tolist(), (time_us / 1000).tolist(),
                    columns["Lat"].tolist(), columns["Lng"].tolist(), columns["Alt"].tolist(), rel_alt,
                    strict=True)]
    problems = [f"{path}: {fast.tail_problem}"] if fast.tail_problem else []
    return _on_clock(rows, path, "unix" if fast.unix else "boot", problems)


def _on_clock(rows: list[dict], path: Path, base: str, problems: list[str]) -> tuple[list[dict], list[str]]:
    chosen, no_fix = with_fix(rows, path)
    for row in chosen:
        row["time_base"] = base
    if chosen and base == "boot":
        problems.append(f"{path}: no GPS time in the log; its times are seconds since boot and cannot be paired "
                        f"with other vehicles' unix times")
    return chosen, problems + no_fix


POSITION_COLUMNS = {"Lat", "Lng", "Alt"}


def _dataflash_positions_dfreader(path: Path, vehicle: str) -> tuple[list[dict], list[str]]:
    from pymavlink import DFReader

    problems: list[str] = []
    with _reference_reader(path, problems):
        try:
            reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
        except Exception as err:  # pymavlink raises bare exceptions on unreadable files
            raise FlightLogError(f"{path}: not a DataFlash log ({err})") from None
        rows: dict[str, list[dict]] = {"POS": [], "GPS": []}
        unusable: set[str] = set()  # a type whose FMT (damaged, or not ArduPilot's) lacks a position column
        while True:
            try:
                msg = reader.recv_match(type=["POS", "GPS"])
            except Exception as err:  # a damaged record: keep what was read before it
                problems.append(f"{path}: a damaged record after {len(rows['POS']) + len(rows['GPS'])} positions "
                                f"({type(err).__name__}: {err}); the rest of the log is not read")
                break
            if msg is None:
                break
            if not set(msg.get_fieldnames()) >= POSITION_COLUMNS:
                unusable.add(msg.get_type())
                continue
            boot_ms = msg.TimeUS / 1000 if hasattr(msg, "TimeUS") else getattr(msg, "TimeMS", None)
            rows[msg.get_type()].append({
                "vehicle": vehicle, "source": "dataflash", "t_s": msg._timestamp, "time_boot_ms": boot_ms,
                "lat_deg": msg.Lat, "lon_deg": msg.Lng, "alt_m": msg.Alt,
                "rel_alt_m": getattr(msg, "RelHomeAlt", None)})
    problems += [f"{path}: {kind} records without the columns {', '.join(sorted(POSITION_COLUMNS))} (as their FMT "
                 f"record describes them): not read as positions" for kind in sorted(unusable)]
    chosen = rows["POS"] or rows["GPS"]
    return _on_clock(chosen, path, "unix" if chosen and chosen[0]["t_s"] > UNIX_TIME_AFTER_S else "boot", problems)


def ulog_positions(path: str | Path, vehicle: str) -> tuple[list[dict], list[str]]:
    """vehicle_global_position rows of a PX4 `.ulg` (the GPS's own when the log has none), on unix time by the
    GPS's UTC stamps; without them, seconds since boot (then said, and the rows' time_base is "boot")."""
    from pyulog import ULog

    path = Path(path)
    check_regular_file(path, "autopilot log", MAX_AUTOPILOT_LOG_BYTES, FlightLogError)  # before pyulog opens it
    topics = ["vehicle_global_position", "vehicle_gps_position", "sensor_gps"]
    problems: list[str] = []
    with _reference_reader(path, problems):
        try:
            ulog = ULog(str(path), message_name_filter_list=topics)
        except Exception as err:  # pyulog raises bare exceptions on unreadable files
            raise FlightLogError(f"{path}: not a ULog file ({err})") from None
    data = {d.name: d.data for d in ulog.data_list}
    offset_us, base = 0, "boot"
    for gps_topic in ("vehicle_gps_position", "sensor_gps"):
        gps = data.get(gps_topic)
        if gps is not None and "time_utc_usec" in gps:
            valid = gps["time_utc_usec"] > 0
            if valid.any():
                offsets = gps["time_utc_usec"][valid].astype("int64") - gps["timestamp"][valid].astype("int64")
                offset_us, base = int(sorted(offsets)[len(offsets) // 2]), "unix"
                break
    if base == "boot":
        problems.append(f"{path}: no GPS UTC time; its times are seconds since boot and cannot be paired with "
                        f"other vehicles' unix times")
    rows = _ulog_rows(data, vehicle, offset_us)
    if rows is None:
        return [], problems + [f"{path}: no positions (none of {', '.join(topics)})"]
    if "vehicle_global_position" not in data:
        problems.append(f"{path}: no vehicle_global_position; positions are the GPS receiver's")
    for row in rows:
        row["time_base"] = base
    rows, no_fix = with_fix(rows, path)
    return rows, problems + no_fix


def _ulog_rows(data: dict, vehicle: str, offset_us: int) -> list[dict] | None:
    """The estimator's positions, else the GPS receiver's (1e-7 degrees and mm in older PX4, degrees and metres
    in sensor_gps since 1.14)."""
    for topic in ("vehicle_global_position", "vehicle_gps_position", "sensor_gps"):
        d = data.get(topic)
        if d is None:
            continue
        if "lat" in d and topic == "vehicle_global_position":
            lat, lon, alt = d["lat"], d["lon"], d["alt"]
        elif "latitude_deg" in d:
            lat, lon, alt = d["latitude_deg"], d["longitude_deg"], d["altitude_msl_m"]
        elif "lat" in d:
            lat, lon, alt = d["lat"] / 1e7, d["lon"] / 1e7, d["alt"] / 1e3
        else:
            continue
        return [{"vehicle": vehicle, "source": "ulog", "t_s": (int(ts) + offset_us) / 1e6,
                 "time_boot_ms": int(ts) / 1000, "lat_deg": float(la), "lon_deg": float(lo), "alt_m": float(al),
                 "rel_alt_m": None}
                for ts, la, lo, al in zip(d["timestamp"], lat, lon, alt, strict=True)]
    return None


def reader_for(path: Path):
    """The position reader of a log, by its extension in any case (ArduPilot writes 00000001.BIN)."""
    return READERS.get(path.suffix.lower())


READERS = {".tlog": tlog_positions, ".bin": dataflash_positions, ".ulg": ulog_positions}
