"""Positions from autopilot logs: MAVLink `.tlog`, ArduPilot DataFlash `.bin`, PX4 `.ulg`.

The one module in `ground/` that imports pymavlink (and pyulog). A `.tlog` is read without pymavlink's
byte-by-byte parser: records are walked by their length fields and only the wanted message types are decoded
(CRC-checked by pymavlink), which is what makes long flights quick to read. Damage is counted, never raised:
bytes that are not a record are skipped up to the next plausible one, frames failing their CRC are dropped.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from ground.logs.dataflash import QUIET_TAIL_BYTES, read_positions_fast  # noqa: E402
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
    """GLOBAL_POSITION_INT rows of a `.tlog` (one vehicle per sysid when `vehicle` is not given), each with the fix
    of the same vehicle's latest GPS_RAW_INT before it (unknown before the first)."""
    read = read_tlog(path, wanted=("GLOBAL_POSITION_INT", "GPS_RAW_INT"))
    positions = [(t_s, msg) for t_s, msg in read.messages if msg.get_type() == "GLOBAL_POSITION_INT"]
    sysids = {msg.get_srcSystem() for _, msg in positions}
    fix_of: dict[int, bool] = {}
    rows = []
    for t_s, msg in read.messages:
        if msg.get_type() == "GPS_RAW_INT":
            fix_of[msg.get_srcSystem()] = msg.fix_type >= MIN_FIX_TYPE
            continue
        name = vehicle if vehicle and len(sysids) == 1 else f"{vehicle or ''}sysid{msg.get_srcSystem()}"
        rows.append({"vehicle": name, "source": "tlog", "t_s": t_s, "time_base": "unix",
                     "time_boot_ms": msg.time_boot_ms, "lat_deg": msg.lat / 1e7, "lon_deg": msg.lon / 1e7,
                     "alt_m": msg.alt / 1000, "rel_alt_m": msg.relative_alt / 1000,
                     "fix": fix_of.get(msg.get_srcSystem())})
    kept, no_fix = [], []
    for name in sorted({r["vehicle"] for r in rows}):
        mine, problems = with_fix([r for r in rows if r["vehicle"] == name], path)
        kept += mine
        no_fix += problems
    return sorted(kept, key=lambda r: r["t_s"]), read.problems + no_fix


UNIX_TIME_AFTER_S = 1e9  # 2001: a smaller time is seconds since boot, not a date
#: GPS_FIX_TYPE_3D_FIX: MAVLink's GPS_RAW_INT.fix_type, PX4's fix_type and ArduPilot's GPS Status share the numbers
MIN_FIX_TYPE = 3
#: No vehicle NAC flies (multicopters, small fixed-wings cruising at 15-30 m/s) covers 100 m in a second; a
#: position that asks for more is a receiver without a fix, or a glitch. Plus a few metres for a fix's own scatter.
MAX_PLAUSIBLE_SPEED_MPS = 100.0
FIX_SCATTER_M = 20.0
EARTH_RADIUS_M = 6_371_000.0


def with_fix(rows: list[dict], path: str | Path) -> tuple[list[dict], list[str]]:
    """Rows with a position, in their order: not those whose receiver had no 3D fix (their "fix" False, where the
    log says), not latitude = longitude = 0 or NaN (what an autopilot logs before its fix), and not those that
    would need an implausible speed from the track around the log's median position (a receiver without a fix
    reports positions a few 1e-7 degrees from 0, 0, thousands of kilometres from where the vehicle flies)."""
    problems = []
    told = [r for r in rows if r.pop("fix", None) is not False]
    if len(told) < len(rows):
        problems.append(f"{path}: {len(rows) - len(told)} of {len(rows)} position samples taken without a 3D fix "
                        f"(the log's GPS fix type below {MIN_FIX_TYPE}) dropped")
    located = [r for r in told if r["lat_deg"] == r["lat_deg"] and r["lon_deg"] == r["lon_deg"]  # not NaN
               and not (r["lat_deg"] == 0.0 and r["lon_deg"] == 0.0)]
    if len(located) < len(told):
        problems.append(f"{path}: {len(told) - len(located)} of {len(rows)} position samples without a fix "
                        f"(latitude = longitude = 0) dropped")
    kept = _plausible(located)
    if len(kept) < len(located):
        problems.append(f"{path}: {len(located) - len(kept)} of {len(rows)} position samples dropped: reaching "
                        f"them would take more than {MAX_PLAUSIBLE_SPEED_MPS:g} m/s from the track around the "
                        f"log's median position (a receiver without a fix, or a glitch)")
    return kept, problems


def _plausible(rows: list[dict]) -> list[dict]:
    """The rows reachable at a plausible speed, walking out in time from the one nearest the median position."""
    if len(rows) < 3:
        return rows
    lat = sorted(r["lat_deg"] for r in rows)[len(rows) // 2]
    lon = sorted(r["lon_deg"] for r in rows)[len(rows) // 2]
    anchor = min(range(len(rows)), key=lambda k: _distance_m(rows[k], lat, lon))
    keep = [False] * len(rows)
    keep[anchor] = True
    for steps in (range(anchor + 1, len(rows)), range(anchor - 1, -1, -1)):
        last = rows[anchor]
        for k in steps:
            dt_s = abs(rows[k]["t_s"] - last["t_s"])
            if _distance_m(rows[k], last["lat_deg"], last["lon_deg"]) <= MAX_PLAUSIBLE_SPEED_MPS * dt_s + FIX_SCATTER_M:
                keep[k], last = True, rows[k]
    return [r for r, kept in zip(rows, keep, strict=True) if kept]


def _distance_m(row: dict, lat_deg: float, lon_deg: float) -> float:
    """Equirectangular: within a flight's extent the error is far below the speed bound's margin."""
    north = math.radians(row["lat_deg"] - lat_deg)
    east = math.radians(row["lon_deg"] - lon_deg) * math.cos(math.radians((row["lat_deg"] + lat_deg) / 2))
    return EARTH_RADIUS_M * math.hypot(north, east)


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


#: a DataFlash record's head (A3 95) and the FMT record's type (128): every ArduPilot log begins with the FMT that
#: describes FMT itself; a file without one near its start (an eeprom image, a parameter file) is not a log
FMT_OF_FMT_HEAD = b"\xa3\x95\x80"
FMT_SEARCH_BYTES = 4096


def dataflash_positions(path: str | Path, vehicle: str) -> tuple[list[dict], list[str]]:
    """POS rows of an ArduPilot DataFlash `.bin` (GPS rows when it has no POS; logs from before 2015 stamp them
    with TimeMS, later ones TimeUS), on pymavlink's clock: unix time from the GPS when the log has it, else
    seconds since boot (then said, and the rows' time_base is "boot"). Modern logs are walked by record length
    (ground.logs.dataflash); the rest go through pymavlink's DFReader."""
    path = Path(path)
    raw = read_bounded(path, "autopilot log", MAX_AUTOPILOT_LOG_BYTES, FlightLogError)
    if FMT_OF_FMT_HEAD not in raw[:FMT_SEARCH_BYTES]:
        raise FlightLogError(f"{path}: not a DataFlash log: no FMT record in its first {FMT_SEARCH_BYTES} bytes "
                             f"(an ArduPilot .bin log starts with one: bytes A3 95 80)")
    fast = read_positions_fast(raw)
    if fast is None:
        return _dataflash_positions_dfreader(path, vehicle)
    pos, gps = fast.columns.get("POS"), fast.columns.get("GPS")
    columns = pos if pos is not None and len(pos["TimeUS"]) else gps
    rows = []
    if columns:
        time_us = columns["TimeUS"]
        rel_alt = columns["RelHomeAlt"].tolist() if "RelHomeAlt" in columns else [None] * len(time_us)
        # the GPS's own rows say whether it had a fix (Status, MAVLink's fix types); POS is the estimator's
        fixed = ((columns["Status"] >= MIN_FIX_TYPE).tolist() if columns is gps and "Status" in columns
                 else [None] * len(time_us))
        rows = [{"vehicle": vehicle, "source": "dataflash", "t_s": t_s, "time_boot_ms": boot_ms, "lat_deg": lat,
                 "lon_deg": lon, "alt_m": alt, "rel_alt_m": rel, "fix": fix}
                for t_s, boot_ms, lat, lon, alt, rel, fix in zip(
                    (fast.timebase_s + time_us * 0.000001).tolist(), (time_us / 1000).tolist(),
                    columns["Lat"].tolist(), columns["Lng"].tolist(), columns["Alt"].tolist(), rel_alt, fixed,
                    strict=True)]
    problems = [f"{path}: {skip_bytes} bytes at offset {offset} are not records (damage); skipped to the next "
                f"record" for offset, skip_bytes in fast.skipped[:CHATTER_LINES]]
    if len(fast.skipped) > CHATTER_LINES:
        problems.append(f"{path}: {len(fast.skipped) - CHATTER_LINES} more damaged places skipped "
                        f"({sum(b for _, b in fast.skipped[CHATTER_LINES:])} bytes)")
    problems += [f"{path}: {fast.tail_problem}"] if fast.tail_problem else []
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
        # DFReader's index of record offsets stops at a header of a type no FMT defined, and a read by type
        # then misses the rest: read every record instead
        indexed = _indexed_to_end(reader)
        while True:
            try:
                msg = reader.recv_match(type=["POS", "GPS"]) if indexed else reader.recv_msg()
                while msg is not None and msg.get_type() not in rows:
                    msg = reader.recv_msg()
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
                "rel_alt_m": getattr(msg, "RelHomeAlt", None),
                "fix": msg.Status >= MIN_FIX_TYPE if hasattr(msg, "Status") else None})
    problems += [f"{path}: {kind} records without the columns {', '.join(sorted(POSITION_COLUMNS))} (as their FMT "
                 f"record describes them): not read as positions" for kind in sorted(unusable)]
    chosen = rows["POS"] or rows["GPS"]
    return _on_clock(chosen, path, "unix" if chosen and chosen[0]["t_s"] > UNIX_TIME_AFTER_S else "boot", problems)


def _indexed_to_end(reader) -> bool:
    """Whether DFReader's index (its offsets per type) reaches the end of the file, bar a padded last page."""
    ends = [offsets[-1] + reader.formats[kind].len for kind, offsets in enumerate(reader.offsets)
            if offsets and kind in reader.formats]
    return bool(ends) and reader.data_len - max(ends) < QUIET_TAIL_BYTES


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
        # the receiver's topics say whether it had a fix (fix_type, MAVLink's numbers); the estimator's do not
        fixed = ([int(f) >= MIN_FIX_TYPE for f in d["fix_type"]] if topic != "vehicle_global_position"
                 and "fix_type" in d else [None] * len(d["timestamp"]))
        return [{"vehicle": vehicle, "source": "ulog", "t_s": (int(ts) + offset_us) / 1e6,
                 "time_boot_ms": int(ts) / 1000, "lat_deg": float(la), "lon_deg": float(lo), "alt_m": float(al),
                 "rel_alt_m": None, "fix": fix}
                for ts, la, lo, al, fix in zip(d["timestamp"], lat, lon, alt, fixed, strict=True)]
    return None


def reader_for(path: Path):
    """The position reader of a log, by its extension in any case (ArduPilot writes 00000001.BIN)."""
    return READERS.get(path.suffix.lower())


READERS = {".tlog": tlog_positions, ".bin": dataflash_positions, ".ulg": ulog_positions}
