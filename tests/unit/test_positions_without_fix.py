"""Positions a receiver reported without a fix are not a trajectory (issue 31): a telemetry log whose GPS had no fix
logged latitudes of a few 1e-7 degrees, and the flight spanned 5,000 km. The fix type the log carries decides where
it has one; otherwise a position that would need more than 100 m/s from the track around the median is dropped."""

import os
import struct

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink  # noqa: E402

from ground.logs.autopilot_logs import tlog_positions, with_fix  # noqa: E402

ZURICH = (47.3977, 8.5456)


def tlog(path, entries):
    """A .tlog of (t_s, message) as MAVProxy writes one: a big-endian µs stamp before each frame."""
    out = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    with open(path, "wb") as f:
        for t_s, msg in entries:
            f.write(struct.pack(">Q", int(t_s * 1e6)) + msg.pack(out))


def position(lat, lon, t_ms):
    return mavlink.MAVLink_global_position_int_message(t_ms, int(lat * 1e7), int(lon * 1e7), 500_000, 10_000,
                                                       0, 0, 0, 0)


def gps(fix_type):
    return mavlink.MAVLink_gps_raw_int_message(0, fix_type, 0, 0, 0, 65535, 65535, 0, 0, 0)


def test_a_tlog_drops_the_positions_its_gps_raw_int_says_had_no_fix(tmp_path):
    t0 = 1.7e9
    entries = [(t0, gps(1))] + [(t0 + k, position(3e-7 * k, 2e-7, k * 1000)) for k in range(1, 6)]
    entries += [(t0 + 6, gps(3))] + [(t0 + 6 + k, position(ZURICH[0] + 1e-5 * k, ZURICH[1], 6000 + k * 1000))
                                     for k in range(10)]
    path = tmp_path / "nofix.tlog"
    tlog(path, entries)
    rows, problems = tlog_positions(path, "uav1")
    assert len(rows) == 10 and all(abs(r["lat_deg"] - ZURICH[0]) < 1e-3 for r in rows)
    assert problems == [f"{path}: 5 of 15 position samples taken without a 3D fix (the log's GPS fix type below 3) "
                        f"dropped"]


def test_without_a_fix_type_positions_out_of_reach_of_the_track_are_dropped_and_counted():
    """No fix type in the log: the three samples near 0, 0 (5,000 km away) and one glitch of 2 km within a second
    are out of reach at 100 m/s; the track, 8 m/s for 30 s, is kept whole."""
    rows = [{"t_s": float(k), "lat_deg": 2e-7 * k, "lon_deg": 1e-7} for k in range(3)]
    rows += [{"t_s": 3.0 + k, "lat_deg": ZURICH[0] + 8 * k / 111_195, "lon_deg": ZURICH[1]} for k in range(30)]
    rows[20] = dict(rows[20], lon_deg=ZURICH[1] + 0.027)  # 2 km east for one sample
    kept, problems = with_fix([dict(r) for r in rows], "log")
    assert [r["t_s"] for r in kept] == [r["t_s"] for r in rows[3:] if r is not rows[20]]
    assert problems == ["log: 4 of 33 position samples dropped: reaching them would take more than 100 m/s from the "
                        "track around the log's median position (a receiver without a fix, or a glitch)"]


def test_a_track_at_plausible_speed_is_kept_whole():
    rows = [{"t_s": 0.2 * k, "lat_deg": ZURICH[0] + 20 * 0.2 * k / 111_195, "lon_deg": ZURICH[1]}
            for k in range(500)]  # 20 m/s, a fixed-wing's cruise, for 100 s
    kept, problems = with_fix([dict(r) for r in rows], "log")
    assert len(kept) == 500 and problems == []
