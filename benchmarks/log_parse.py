"""Reading positions from autopilot logs, NAC's readers against pymavlink's on the same file, in the same run.

- a 1,000,000-message `.tlog`: `read_tlog` (walks records by their length fields and decodes only
  GLOBAL_POSITION_INT) against pymavlink's `mavutil` loop (target: at least 2x faster). The file mixes what a
  companion link carries: per 10 messages, 1 GLOBAL_POSITION_INT, 2 ATTITUDE, 2 LOCAL_POSITION_NED,
  1 HEARTBEAT, 1 SYS_STATUS, 1 GPS_RAW_INT, 1 VFR_HUD, 1 MISSION_CURRENT.
- a modern ArduPilot DataFlash `.bin` of --dataflash-records records (per 10: 1 POS, 1 GPS, 4 ATT, 4 IMU, all
  stamped TimeUS, GPS time as GWk/GMS): `dataflash_positions` against DFReader's `recv_match` over POS and GPS,
  which is how positions were read before (target: at least 3x faster), with the same rows and times; each
  the best of three reads.

    python benchmarks/log_parse.py [--messages 1000000] [--dataflash-records 100000] [--smoke]
"""

from __future__ import annotations

import argparse
import io
import os
import struct
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from ground.logs.autopilot_logs import dataflash_positions, read_tlog  # noqa: E402

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SMOKE = {"messages": 5000, "dataflash_records": 2000}  # --smoke: small files, the same reads


def write_tlog(path: Path, messages: int) -> int:
    mav = mavlink.MAVLink(io.BytesIO(), srcSystem=1, srcComponent=1)
    mix = [
        mavlink.MAVLink_global_position_int_message(0, 473977420, 85455940, 491000, 3000, 10, 20, 0, 9000),
        mavlink.MAVLink_attitude_message(0, 0.01, 0.02, 1.5, 0.0, 0.0, 0.0),
        mavlink.MAVLink_local_position_ned_message(0, 1.0, 2.0, -3.0, 0.1, 0.2, 0.0),
        mavlink.MAVLink_heartbeat_message(2, 3, 89, 3, 4, 3),
        mavlink.MAVLink_sys_status_message(0, 0, 0, 500, 12600, 1000, 90, 0, 0, 0, 0, 0, 0),
        mavlink.MAVLink_gps_raw_int_message(0, 3, 473977420, 85455940, 491000, 80, 100, 50, 9000, 12),
        mavlink.MAVLink_vfr_hud_message(0.5, 0.5, 90, 50, 3.0, 0.0),
        mavlink.MAVLink_mission_current_message(2),
    ]
    order = [0, 1, 1, 2, 2, 3, 4, 5, 6, 7]
    frames = [m.pack(mav) for m in mix]
    t_us = 1_700_000_000_000_000
    wanted = 0
    with open(path, "wb") as f:
        chunk = []
        for k in range(messages):
            which = order[k % 10]
            wanted += which == 0
            chunk.append(struct.pack(">Q", t_us + 1000 * k) + frames[which])
            if len(chunk) == 10000:
                f.write(b"".join(chunk))
                chunk = []
        f.write(b"".join(chunk))
    return wanted


DF_FORMATS = {  # type: (name, format, columns)
    129: ("POS", "QLLfff", "TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt"),
    130: ("GPS", "QBIHBcLLeffffB", "TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,Yaw,U"),
    131: ("ATT", "QccccCCCC", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw"),
    132: ("IMU", "QffffffIIfBB", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH"),
}
DF_CODES = {"Q": "Q", "L": "i", "f": "f", "B": "B", "I": "I", "H": "H", "c": "h", "e": "i", "C": "H"}


def write_dataflash(path: Path, records: int) -> int:
    """A modern DataFlash log: the FMT records, then `records` records at 100 Hz; returns the POS count."""
    head = b"\xa3\x95"
    out = [head + bytes([128]) + struct.pack("<BB4s16s64s", 128, 89, b"FMT", b"BBnNZ",
                                             b"Type,Length,Name,Format,Columns")]
    packers = {}
    for kind, (name, fmt, columns) in DF_FORMATS.items():
        packer = struct.Struct("<" + "".join(DF_CODES[c] for c in fmt))
        packers[name] = (kind, packer)
        out.append(head + bytes([128]) + struct.pack("<BB4s16s64s", kind, 3 + packer.size, name.encode(),
                                                     fmt.encode(), columns.encode()))
    order = ["POS", "GPS", "ATT", "ATT", "IMU", "IMU", "ATT", "ATT", "IMU", "IMU"]
    positions = 0
    for k in range(records):
        t_us = 60_000_000 + 10_000 * k
        name = order[k % 10]
        kind, packer = packers[name]
        if name == "POS":
            values = (t_us, 473977420 + k, 85455940 - k, 488.0 + 0.001 * k, 10.0, 10.0)
            positions += 1
        elif name == "GPS":
            values = (t_us, 3, 302_400_000 + t_us // 1000, 2290, 12, 80, 473977420 + k, 85455940 - k, 48825,
                      5.0, 90.0, 0.1, 0.0, 1)
        elif name == "ATT":
            values = (t_us, 1, 2, 3, 4, 5, 6, 7, 8)
        else:
            values = (t_us, 0.1, 0.2, 0.3, 0.0, 0.0, -9.8, 0, 0, 25.0, 1, 1)
        out.append(head + bytes([kind]) + packer.pack(*values))
    path.write_bytes(b"".join(out))
    return positions


def dfreader_positions(path: Path) -> list:
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    rows = []
    while (msg := reader.recv_match(type=["POS", "GPS"])) is not None:
        if msg.get_type() == "POS":
            rows.append((msg._timestamp, msg.Lat, msg.Lng))
    return rows


def _best_of(repeats: int, read):
    """The fastest of `repeats` reads (both readers get the same warm page cache) and what the read returned."""
    best_s, result = float("inf"), None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = read()
        best_s = min(best_s, time.perf_counter() - t0)
    return best_s, result


def compare_dataflash(tmp: Path, records: int) -> None:
    path = tmp / "bench.bin"
    expected = write_dataflash(path, records)
    print(f"{path.stat().st_size / 1e6:.2f} MB DataFlash, {records:,} records, {expected:,} POS")
    ours_s, (rows, problems) = _best_of(3, lambda: dataflash_positions(path, "bench"))
    theirs_s, reference = _best_of(3, lambda: dfreader_positions(path))
    same = len(rows) == len(reference) == expected and all(
        abs(r["t_s"] - t) < 1e-6 and r["lat_deg"] == lat and r["lon_deg"] == lon
        for r, (t, lat, lon) in zip(rows, reference, strict=True))
    if not same or problems:
        raise SystemExit(f"dataflash_positions differs from DFReader: {len(rows)} vs {len(reference)} rows, "
                         f"problems {problems[:3]}")
    print(f"nac dataflash_positions: {ours_s:6.3f} s  {records / ours_s:10,.0f} records/s")
    print(f"DFReader recv_match:     {theirs_s:6.3f} s  {records / theirs_s:10,.0f} records/s")
    print(f"speed-up: {theirs_s / ours_s:.1f}x (target >= 3x), the same {expected:,} rows and times")


def mavutil_positions(path: Path) -> tuple[int, int]:
    log = mavutil.mavlink_connection(str(path))
    seen = wanted = 0
    while True:
        msg = log.recv_msg()
        if msg is None:
            break
        seen += 1
        wanted += msg.get_type() == "GLOBAL_POSITION_INT"
    return seen, wanted


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--messages", type=int, default=1_000_000)
    parser.add_argument("--dataflash-records", type=int, default=100_000)
    args = _common.parse_args(parser, SMOKE)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bench.tlog"
        expected = write_tlog(path, args.messages)
        print(f"{path.stat().st_size / 1e6:.1f} MB, {args.messages:,} messages, {expected:,} GLOBAL_POSITION_INT")
        t0 = time.perf_counter()
        read = read_tlog(path)
        ours_s = time.perf_counter() - t0
        if len(read.messages) != expected or read.frames != args.messages or read.problems:
            raise SystemExit(f"read_tlog: {len(read.messages)} of {expected} positions, {read.frames} of "
                             f"{args.messages} frames, problems {read.problems[:3]}")
        t0 = time.perf_counter()
        seen, wanted = mavutil_positions(path)
        theirs_s = time.perf_counter() - t0
        if wanted != expected:
            raise SystemExit(f"mavutil found {wanted} of {expected} positions")
        print(f"nac read_tlog:   {ours_s:6.2f} s  {args.messages / ours_s:10,.0f} messages/s")
        print(f"mavutil loop:    {theirs_s:6.2f} s  {seen / theirs_s:10,.0f} messages/s")
        print(f"speed-up: {theirs_s / ours_s:.1f}x (target >= 2x)")
        compare_dataflash(Path(tmp), args.dataflash_records)


if __name__ == "__main__":
    main()
