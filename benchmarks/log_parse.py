"""Reading positions from a 1,000,000-message `.tlog`: NAC's reader (walks records by their length fields and
decodes only GLOBAL_POSITION_INT) against pymavlink's own `mavutil` loop over the same file, in the same run
(target: at least 2x faster).

The file mixes what a companion link carries: per 10 messages, 1 GLOBAL_POSITION_INT, 2 ATTITUDE,
2 LOCAL_POSITION_NED, 1 HEARTBEAT, 1 SYS_STATUS, 1 GPS_RAW_INT, 1 VFR_HUD, 1 MISSION_CURRENT.

    python benchmarks/log_parse.py [--messages 1000000] [--smoke]
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

from ground.logs.autopilot_logs import read_tlog  # noqa: E402

import _common  # noqa: E402 (benchmarks/_common.py, beside this script)

SMOKE = {"messages": 5000}  # --smoke: a small file, the same reads


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


if __name__ == "__main__":
    main()
