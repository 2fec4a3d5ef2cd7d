"""Synthesized flight logs for test fixtures.

No ArduPilot or PX4 instance runs in the test environment, so these helpers write
small but valid logs directly with ``struct``:

* ``write_dataflash`` -- ArduPilot DataFlash binary log (``.bin``), readable by
  pymavlink's ``DFReader`` (``mavutil.mavlink_connection(path)``).
* ``write_ulog`` -- PX4 ULog (``.ulg``), readable by ``pyulog.ULog``.

``samples`` is a list of ``(t_unix_s, lat_deg, lon_deg, alt_m)`` tuples and
``boot_unix_s`` is the unix time of vehicle boot; log timestamps are microseconds
since boot, i.e. ``(t_unix_s - boot_unix_s) * 1e6``.
"""

import struct

GPS_EPOCH_UNIX_S = 315964800  # 1980-01-06T00:00:00Z
GPS_LEAP_SECONDS = 18  # GPS - UTC since 2017
SECONDS_PER_WEEK = 7 * 86400


def _us_since_boot(t_unix_s, boot_unix_s):
    return int(round((t_unix_s - boot_unix_s) * 1e6))


def _gps_week_ms(t_unix_s):
    """Unix time -> (GPS week, milliseconds into the week)."""
    gps_ms = int(round((t_unix_s - GPS_EPOCH_UNIX_S + GPS_LEAP_SECONDS) * 1000))
    return divmod(gps_ms, SECONDS_PER_WEEK * 1000)


# --- ArduPilot DataFlash ------------------------------------------------------

DF_HEAD = b"\xa3\x95"
DF_FMT_TYPE = 128
# format char -> struct code (subset of ArduPilot's, see pymavlink DFReader.FORMAT_TO_STRUCT)
DF_STRUCT = {"B": "B", "H": "H", "I": "I", "Q": "Q", "c": "h", "e": "i", "f": "f",
             "L": "i", "n": "4s", "N": "16s", "Z": "64s"}
# (type id, name, format chars, columns) -- layouts as in ArduPilot 4.0
DF_MESSAGES = [
    (DF_FMT_TYPE, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"),
    (130, "GPS", "QBIHBcLLefffB", "TimeUS,Status,GMS,GWk,NSats,HDop,Lat,Lng,Alt,Spd,GCrs,VZ,U"),
    (131, "POS", "QLLfff", "TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt"),
]


def _df_struct(fmt):
    return struct.Struct("<" + "".join(DF_STRUCT[c] for c in fmt))


def write_dataflash(path, samples, boot_unix_s):
    """Write an ArduPilot DataFlash log with one GPS and one POS message per sample.

    Units follow ArduPilot: Lat/Lng degrees*1e7 (int32), GPS.Alt centimetres (int32),
    POS.Alt metres AMSL (float), HDop*100, GWk/GMS GPS week and ms of week.
    """
    structs = {name: (msg_type, _df_struct(fmt)) for msg_type, name, fmt, _ in DF_MESSAGES}

    def record(name, *values):
        msg_type, st = structs[name]
        return DF_HEAD + bytes([msg_type]) + st.pack(*values)

    out = bytearray()
    for msg_type, name, fmt, columns in DF_MESSAGES:
        length = 3 + _df_struct(fmt).size
        out += record("FMT", msg_type, length, name.encode(), fmt.encode(), columns.encode())
    for t_unix_s, lat, lon, alt in samples:
        time_us = _us_since_boot(t_unix_s, boot_unix_s)
        week, ms = _gps_week_ms(t_unix_s)
        lat_e7, lon_e7 = int(round(lat * 1e7)), int(round(lon * 1e7))
        out += record("GPS", time_us, 3, ms, week, 12, 80, lat_e7, lon_e7, int(round(alt * 100)),
                      0.0, 0.0, 0.0, 1)
        out += record("POS", time_us, lat_e7, lon_e7, alt, alt, alt)
    with open(path, "wb") as f:
        f.write(out)


# --- PX4 ULog -------------------------------------------------------------------

ULOG_MAGIC = b"ULog\x01\x12\x35"
ULOG_VERSION = 1
ULOG_TOPICS = [  # (msg_id, topic, [(ulog type, field name)]), declared in packed order
    (0, "vehicle_global_position",
     [("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"), ("float", "alt")]),
    (1, "vehicle_gps_position",
     [("uint64_t", "timestamp"), ("uint64_t", "time_utc_usec"), ("int32_t", "lat"),
      ("int32_t", "lon"), ("int32_t", "alt")]),
]
ULOG_STRUCT = {"uint64_t": "Q", "int32_t": "i", "double": "d", "float": "f"}


def _ulog_msg(msg_type, payload):
    return struct.pack("<HB", len(payload), ord(msg_type)) + payload


def write_ulog(path, samples, boot_unix_s):
    """Write a PX4 ULog with vehicle_global_position and vehicle_gps_position per sample.

    vehicle_global_position: lat/lon degrees (double), alt metres AMSL (float).
    vehicle_gps_position: time_utc_usec unix µs, lat/lon degrees*1e7, alt millimetres.
    ``timestamp`` is µs since boot in both topics.
    """
    structs = {name: struct.Struct("<" + "".join(ULOG_STRUCT[t] for t, _ in fields))
               for _, name, fields in ULOG_TOPICS}
    first_us = min((_us_since_boot(s[0], boot_unix_s) for s in samples), default=0)

    out = bytearray(ULOG_MAGIC + bytes([ULOG_VERSION]) + struct.pack("<Q", first_us))
    # Flag bits: compat[8], incompat[8], appended_offsets[3] -- all zero.
    out += _ulog_msg("B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    for _, name, fields in ULOG_TOPICS:
        out += _ulog_msg("F", f"{name}:{''.join(f'{t} {n};' for t, n in fields)}".encode())
    for msg_id, name, _ in ULOG_TOPICS:
        out += _ulog_msg("A", struct.pack("<BH", 0, msg_id) + name.encode())
    for t_unix_s, lat, lon, alt in samples:
        ts = _us_since_boot(t_unix_s, boot_unix_s)
        utc_us = int(round(t_unix_s * 1e6))
        rows = {
            "vehicle_global_position": (ts, lat, lon, alt),
            "vehicle_gps_position": (ts, utc_us, int(round(lat * 1e7)), int(round(lon * 1e7)),
                                     int(round(alt * 1000))),
        }
        for msg_id, name, _ in ULOG_TOPICS:
            out += _ulog_msg("D", struct.pack("<H", msg_id) + structs[name].pack(*rows[name]))
    with open(path, "wb") as f:
        f.write(out)
