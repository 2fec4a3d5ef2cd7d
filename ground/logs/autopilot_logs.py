"""Positions from autopilot logs: MAVLink `.tlog`, ArduPilot DataFlash `.bin`, PX4 `.ulg`.

The one module in `ground/` that imports pymavlink (and pyulog). A `.tlog` is read without pymavlink's
byte-by-byte parser: records are walked by their length fields and only the wanted message types are decoded
(CRC-checked by pymavlink), which is what makes long flights quick to read. Damage is counted, never raised:
bytes that are not a record are skipped up to the next plausible one, frames failing their CRC are dropped.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from nac_onboard.errors import BadInput
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
    try:
        data = path.read_bytes()
    except OSError as err:
        raise FlightLogError(f"{path}: cannot read ({err.strerror})") from None
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
             "source": "tlog", "t_s": t_s,
             "time_boot_ms": msg.time_boot_ms, "lat_deg": msg.lat / 1e7, "lon_deg": msg.lon / 1e7,
             "alt_m": msg.alt / 1000, "rel_alt_m": msg.relative_alt / 1000}
            for t_s, msg in read.messages]
    return rows, read.problems


def dataflash_positions(path: str | Path, vehicle: str) -> tuple[list[dict], list[str]]:
    """POS rows of an ArduPilot DataFlash `.bin` (GPS rows when it has no POS), on pymavlink's unix clock."""
    from pymavlink import DFReader

    path = Path(path)
    try:
        reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    except Exception as err:  # pymavlink raises bare exceptions on unreadable files
        raise FlightLogError(f"{path}: not a DataFlash log ({err})") from None
    rows = {"POS": [], "GPS": []}
    while True:
        try:
            msg = reader.recv_match(type=["POS", "GPS"])
        except Exception:  # a damaged tail: keep what was read
            break
        if msg is None:
            break
        kind = msg.get_type()
        rows[kind].append({"vehicle": vehicle, "source": "dataflash", "t_s": msg._timestamp,
                           "time_boot_ms": msg.TimeUS / 1000, "lat_deg": msg.Lat, "lon_deg": msg.Lng,
                           "alt_m": msg.Alt, "rel_alt_m": getattr(msg, "RelHomeAlt", None)})
    return rows["POS"] or rows["GPS"], []


def ulog_positions(path: str | Path, vehicle: str) -> tuple[list[dict], list[str]]:
    """vehicle_global_position rows of a PX4 `.ulg`, put on unix time by the GPS's UTC stamps."""
    from pyulog import ULog

    path = Path(path)
    topics = ["vehicle_global_position", "vehicle_gps_position", "sensor_gps"]
    try:
        ulog = ULog(str(path), message_name_filter_list=topics)
    except Exception as err:  # pyulog raises bare exceptions on unreadable files
        raise FlightLogError(f"{path}: not a ULog file ({err})") from None
    data = {d.name: d.data for d in ulog.data_list}
    problems = []
    offset_us = None
    for gps_topic in ("vehicle_gps_position", "sensor_gps"):
        gps = data.get(gps_topic)
        if gps is not None and "time_utc_usec" in gps:
            valid = gps["time_utc_usec"] > 0
            if valid.any():
                offsets = gps["time_utc_usec"][valid].astype("int64") - gps["timestamp"][valid].astype("int64")
                offset_us = int(sorted(offsets)[len(offsets) // 2])
                break
    if offset_us is None:
        offset_us = int(ulog.start_timestamp)
        problems.append(f"{path}: no GPS UTC time; times are seconds since boot, not aligned with other logs")
    pos = data.get("vehicle_global_position")
    if pos is None:
        return [], problems + [f"{path}: no vehicle_global_position topic"]
    rows = [{"vehicle": vehicle, "source": "ulog", "t_s": (int(ts) + offset_us) / 1e6, "time_boot_ms": int(ts) / 1000,
             "lat_deg": float(lat), "lon_deg": float(lon), "alt_m": float(alt), "rel_alt_m": None}
            for ts, lat, lon, alt in zip(pos["timestamp"], pos["lat"], pos["lon"], pos["alt"], strict=True)]
    return rows, problems


READERS = {".tlog": tlog_positions, ".bin": dataflash_positions, ".ulg": ulog_positions}
