"""Positions from an ArduPilot DataFlash `.bin` without decoding every record: records are walked by the lengths
their FMT records give, and only POS and GPS are unpacked, on the clock pymavlink's DFReader would give them.

The walk is done on arrays rather than record by record: every place the two header bytes occur is a candidate
record, each candidate points at the one its length says comes next, and the records are the candidates reached
from offset 0 (found by pointer doubling, log2(n) array steps). Header bytes that happen to sit inside a payload
are candidates no chain from 0 reaches.

Damage (bytes that are not a record, a header of a type no FMT defined) ends a chain; the walk goes on at the next
candidate whose length leads to another record, as DFReader's sequential read skips bad bytes, and says how many
bytes it skipped where. Requiring the record after it (DFReader takes the first known header) keeps header bytes in
a damaged payload from being read as a record.

This path takes the logs ArduPilot has written since 2015 (every record stamped with TimeUS, GPS time as
GWk/GMS). Anything else (older TimeMS logs, an FMT defined twice or off the chain) returns None, and the caller
reads the file with DFReader: same rows, only slower.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

HEAD = (0xA3, 0x95)
FMT_TYPE = 128
FMT_STRUCT = struct.Struct("<BB4s16s64s")  # Type, Length (with the 3-byte head), Name, Format, Columns
FMT_LENGTH = 3 + FMT_STRUCT.size
FMT_OF_FMT = (FMT_LENGTH, b"BBnNZ", b"Type,Length,Name,Format,Columns")
#: DataFlash format characters: numpy type and the divisor of the scaled ones (dividing by 1e7 rather than
#: multiplying by 1e-7 is more accurate, and it is what DFReader does)
CODES = {"a": ("S64", None), "b": ("i1", None), "B": ("u1", None), "g": ("<f2", None), "h": ("<i2", None),
         "H": ("<u2", None), "i": ("<i4", None), "I": ("<u4", None), "f": ("<f4", None), "n": ("S4", None),
         "N": ("S16", None), "Z": ("S64", None), "c": ("<i2", 100.0), "C": ("<u2", 100.0), "e": ("<i4", 100.0),
         "E": ("<u4", 100.0), "L": ("<i4", 1.0e7), "d": ("<f8", None), "M": ("i1", None), "q": ("<i8", None),
         "Q": ("<u8", None)}
GPS_EPOCH_S = 86400 * (10 * 365 + int((1980 - 1969) / 4) + 1 + 6 - 2)  # 1980-01-06 in unix time
GPS_LEAP_S = 18  # as DFReader counts it
#: DFReader says nothing of bytes that are not a record this close to the end (block logs pad their last page)
QUIET_TAIL_BYTES = 528


@dataclass
class Format:
    name: str
    length: int
    dtype: np.dtype
    divisors: dict[str, float]

    def decode(self, data: np.ndarray, offsets: np.ndarray) -> dict[str, np.ndarray]:
        """Columns of the records at `offsets`, scaled as DFReader scales them."""
        payload = data[offsets[:, None] + np.arange(3, self.length)]
        records = np.ascontiguousarray(payload).view(self.dtype).ravel()
        return {c: records[c] / self.divisors[c] if c in self.divisors else records[c] for c in self.dtype.names}


@dataclass
class FastRead:
    columns: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # POS and GPS columns, in file order
    tail_problem: str | None = None  # what was skipped at the end, said as a sentence
    skipped: list[tuple[int, int]] = field(default_factory=list)  # (offset, bytes) of damage walked over
    timebase_s: float = 0.0
    unix: bool = False  # the timebase came from GPS time (else seconds since boot)


def _format(body: bytes) -> tuple[int, Format | None] | None:
    """The type an FMT record defines and its layout (None for the FMT type itself); None if it does not parse."""
    kind, length, name, fmt, columns = FMT_STRUCT.unpack(body)
    if kind == FMT_TYPE:  # any other description of FMT itself is DFReader's to judge
        return (kind, None) if (length, fmt.rstrip(b"\0"), columns.rstrip(b"\0")) == FMT_OF_FMT else None
    chars = fmt.rstrip(b"\0").decode("ascii", "replace")
    names = columns.rstrip(b"\0").decode("ascii", "replace").split(",") if columns.strip(b"\0") else []
    if any(c not in CODES for c in chars) or len(names) != len(chars) or len(set(names)) != len(names):
        return None
    if not all(n.isascii() and n.replace("_", "a").isalnum() for n in names):
        return None  # damage in the column names: DFReader's to judge
    dtype = np.dtype([(n, CODES[c][0]) for n, c in zip(names, chars, strict=True)])
    if dtype.itemsize + 3 != length:
        return None
    divisors = {n: CODES[c][1] for n, c in zip(names, chars, strict=True) if CODES[c][1] is not None}
    return kind, Format(name.rstrip(b"\0").decode("ascii", "replace"), length, dtype, divisors)


def _formats(data: np.ndarray, starts: np.ndarray) -> tuple[dict[int, Format], set[int]] | None:
    """Every FMT candidate that parses, by type; None where two disagree. Also the offsets of those that parsed."""
    formats: dict[int, Format] = {}
    used: set[int] = set()
    for start in starts[data[starts + 2] == FMT_TYPE]:
        parsed = _format(data[start + 3:start + FMT_LENGTH].tobytes()) if start + FMT_LENGTH <= len(data) else None
        if parsed is None:
            continue
        kind, fmt = parsed
        used.add(int(start))
        if fmt is None:
            continue
        if kind in formats and formats[kind] != fmt:
            return None
        formats[kind] = fmt
    return formats, used


def _chain(nxt: np.ndarray) -> np.ndarray:
    """Mask of the nodes reached from node 0 by following `nxt` (the last node is a sink pointing at itself):
    after step k the mask holds the first 2**k nodes of the path, so log2(n) steps find it all."""
    on = np.zeros(len(nxt), dtype=bool)
    on[0] = True
    jump = nxt
    for _ in range(max(1, int(len(nxt)).bit_length())):
        on[jump[on]] = True
        jump = jump[jump]
    return on


def read_positions_fast(raw: bytes, wanted=("POS", "GPS")) -> FastRead | None:
    """The wanted records of a modern DataFlash log and its clock, or None where DFReader must read it."""
    data = np.frombuffer(raw, dtype=np.uint8)
    n = len(data)
    if n < 3 or (data[0], data[1]) != HEAD:
        return None
    starts = np.flatnonzero((data[:-2] == HEAD[0]) & (data[1:-1] == HEAD[1]))
    parsed = _formats(data, starts)
    if parsed is None:
        return None
    formats, fmt_offsets = parsed
    lengths = np.zeros(256, dtype=np.int64)  # 0: no FMT for the type
    lengths[FMT_TYPE] = FMT_LENGTH
    for kind, fmt in formats.items():
        lengths[kind] = fmt.length
    kinds = data[starts + 2]
    record_lengths = lengths[kinds]
    ends = starts + record_lengths
    sink = len(starts)
    nxt = np.searchsorted(starts, ends)
    known = record_lengths > 0
    linked = known & (nxt < sink) & (starts[np.minimum(nxt, sink - 1)] == ends)
    last = known & (ends == n)
    following = np.minimum(nxt, sink - 1)
    # where a chain may go on after damage: a record whose length leads to another record (or ends the file)
    good = np.flatnonzero(linked & (linked[following] | last[following]))
    dead = np.flatnonzero(~linked & ~last)
    walk_end = np.where(known, ends, starts)  # where damage after a node begins: its end, or a header of no type
    pick = np.searchsorted(starts[good], walk_end[dead])
    nxt[~linked] = sink
    nxt[dead] = np.where(pick < len(good), good[np.minimum(pick, len(good) - 1)], sink) if len(good) else sink
    on = _chain(np.append(nxt, sink))[:sink]
    chain = np.flatnonzero(on)
    final = int(chain[-1])
    resumed = chain[:-1][~linked[chain[:-1]]]  # chain nodes whose next record is past damage
    skipped = [(int(walk_end[k]), int(starts[nxt[k]] - walk_end[k])) for k in resumed.tolist()]
    keep = chain[known[chain] & (ends[chain] <= n)]
    records, record_kinds = starts[keep], kinds[keep]
    tail_problem = _tail(n, int(walk_end[final]))
    on_chain = set(records[record_kinds == FMT_TYPE].tolist())
    if not fmt_offsets <= on_chain or len(on_chain) != len(fmt_offsets):
        return None  # an FMT that is not a record, or a record FMT that did not parse
    out = FastRead(tail_problem=tail_problem, skipped=skipped)
    by_name = {f.name: (kind, f) for kind, f in formats.items()}
    for name in wanted:
        if name not in by_name:
            continue
        kind, fmt = by_name[name]
        if fmt.dtype.names[0] != "TimeUS" or not {"Lat", "Lng", "Alt"} <= set(fmt.dtype.names):
            return None  # a log stamped in TimeMS (DFReader's older clocks), or a layout that is not ArduPilot's
        out.columns[name] = fmt.decode(data, records[record_kinds == kind])
    return out if _set_clock(out, by_name.get("GPS", (0, None))[1]) else None


def _tail(n: int, end: int) -> str | None:
    """What ends the walk at `end` (the last record's end, or the header of no known type that ended it): None for
    the end of the file, else a sentence (DFReader skips a cut record and a short tail quietly)."""
    if end == n:
        return None
    if end > n:
        return "the last record is cut short (the writer stopped mid-record); skipped"
    if n - end < QUIET_TAIL_BYTES:
        return f"{n - end} bytes after the last record are not a record; skipped"
    return f"{n - end} bytes from offset {end} to the end are not records (damage); skipped"


def _set_clock(read: FastRead, gps: Format | None) -> bool:
    """DFReader's microsecond clock: the first GPS record with a GPS week sets unix time; a log whose GPS never
    has one (or has no GPS) stays on seconds since boot. A GPS without GWk/GMS is an older log: not this path."""
    columns = read.columns.get("GPS")
    if gps is None or columns is None or not len(columns["TimeUS"]):
        return True
    if not {"GWk", "GMS"} <= set(gps.dtype.names):
        return False
    with_week = np.flatnonzero(columns["GWk"] > 0)
    if len(with_week):
        k = with_week[0]
        week, week_ms, time_us = int(columns["GWk"][k]), int(columns["GMS"][k]), int(columns["TimeUS"][k])
        t = GPS_EPOCH_S + 86400 * 7 * week + week_ms * 0.001 - GPS_LEAP_S
        read.timebase_s, read.unix = t - time_us * 0.000001, True
    return True
