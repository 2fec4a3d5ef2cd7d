"""One reader for live and replay: the records of a run directory, read as they are appended, each turned into
the small frame the page draws (positions in local metres, probes, iterations, link capacities, events).

    each vehicle's agent log     telemetry and events       -> "pos" (a batch), "ev"
    the master's probes          iperf3-shaped results      -> "probe"
    the MPI job's records        its iterations             -> "it"
    the kernel network's log     the link model's capacities -> "cap"
    the experiment's log         the runner's faults        -> "ev"
    the energy log               each vehicle's packs        -> "pw" (state of charge, flight and companion)

(files and kinds as nac_onboard/records names them: docs/records.md)

A "pos" frame holds every position one read of a vehicle's file gave, as columns ("t", "e", "n", "u", "hdg",
"mode", "armed", "batt", "seq", "tot", "tb", one entry per record): a replay's hundred thousand positions are
sixteen frames, read, sent and parsed as arrays instead of one object each.

Live, a file's last line may still be being written: it waits for its newline. A line that is not JSON, or a
record without what it needs, is skipped and named in `problems` (file and line); what no file holds is in
`missing`. Nothing here raises for a damaged run.

Every file is hostile until checked: a line longer than MAX_LINE_BYTES is skipped as it is read (never held
whole: a 200 MB record costs a megabyte of memory) and named; a file is read at most MAX_READ_BYTES per poll;
a record whose t_s is more than MAX_GAP_S from the run's span (first the median of the first read's records,
then growing with the records kept), or more than MAX_GAP_S ahead of this machine's clock, is skipped and named,
so one wild timestamp cannot stretch the timeline to the year 30000; texts and ids passed to the page are cut
short, and a frame holds at most MAX_FRAME_POSITIONS positions.
"""

from __future__ import annotations

import contextlib
import gc
import math
import operator
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

from missions.geo import Home, lla_to_enu
from nac_onboard.flight_log import finite_number as _finite
from nac_onboard.records import READABLE_VERSIONS, kinds

EVENT_KINDS = {k.name: text for k, text in (
    (kinds.LINK_LOST, "autopilot link lost"), (kinds.LINK_RESTORED, "autopilot link back"), (kinds.PEER_LOST, "lost"),
    (kinds.PEER_SEEN, "seen"), (kinds.MISSION_ITEM_REACHED, "reached item"), (kinds.LANDED_STATE, "landed state"),
    (kinds.AGENT_STARTED, "agent started"), (kinds.MODE, "mode"), (kinds.STATUSTEXT, "says"))}
MAX_LINE_BYTES = 1 << 20  # a longer line is skipped and named, never held whole
READ_CHUNK_BYTES = 1 << 20
MAX_READ_BYTES = 32 << 20  # per file and poll: the rest on the next poll (live) or the next round (finish)
MAX_GAP_S = 86_400.0  # a record more than a day from the run's span, or ahead of the clock, is not of this run
MAX_FRAME_POSITIONS = 20_000  # positions in one "pos" frame: every frame, and so every response, is bounded
MAX_TEXT_CHARS = 200  # an event's text as the page shows it
MAX_ID_CHARS = 64  # a vehicle id or a role from a record
SOURCES = {kinds.AGENT_LOG.name: "agent", kinds.THROUGHPUT_LOG.name: "throughput", kinds.COMPUTE_LOG.name: "compute",
           kinds.NETWORK_LOG.name: "network", kinds.EXPERIMENT_LOG.name: "experiment", kinds.ENERGY_LOG.name: "energy"}
TELEMETRY = kinds.TELEMETRY.name


@dataclass
class _Tail:
    """A file read from where the last read stopped, whole lines only."""

    path: Path
    offset: int = 0
    line_no: int = 0
    partial: bytes = b""
    skipping: int = 0  # bytes so far of a line over MAX_LINE_BYTES, dropped as they are read (0: none)
    pending: bool = False  # the last read stopped at MAX_READ_BYTES: more to read now
    oversized: list = field(default_factory=list)  # (line number, bytes) of lines skipped for their size

    def new_lines(self) -> list[tuple[int, bytes]]:
        """The whole lines added since the last call (at most MAX_READ_BYTES of the file; `pending` says more is
        there). A line over MAX_LINE_BYTES goes to `oversized` instead, and is never held whole."""
        out: list[tuple[int, bytes]] = []
        self.pending = False
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                budget = MAX_READ_BYTES
                while budget > 0:
                    data = f.read(min(READ_CHUNK_BYTES, budget))
                    if not data:
                        break
                    budget -= len(data)
                    self.offset += len(data)
                    self._split(data, out)
                else:
                    self.pending = True
        except OSError:
            pass
        return out

    def _split(self, data: bytes, out: list) -> None:
        pieces = data.split(b"\n")
        last = pieces.pop()
        for piece in pieces:
            self.line_no += 1
            if self.skipping or self.partial:
                size = self.skipping + len(self.partial) + len(piece)
                line = b"" if self.skipping else self.partial + piece
                self.skipping, self.partial = 0, b""
            else:
                size, line = len(piece), piece
            if size > MAX_LINE_BYTES:
                self.oversized.append((self.line_no, size))
            elif line.strip():
                out.append((self.line_no, line))
        if self.skipping:
            self.skipping += len(last)
        elif len(self.partial) + len(last) > MAX_LINE_BYTES:  # not a line being written: dropped as it comes
            self.skipping, self.partial = len(self.partial) + len(last), b""
        else:
            self.partial += last


@dataclass
class RunFollower:
    run_dir: Path | None  # None: no files, only what live sources add
    records: list[dict] = field(default_factory=list)  # every frame so far, in arrival order; "s" is its index
    vehicles: dict[str, dict] = field(default_factory=dict)  # id -> {"role": ...}
    problems: list[str] = field(default_factory=list)
    origin: Home | None = None  # the map's (0, 0): the first position heard, at ground level
    mission_lla: dict[str, list] = field(default_factory=dict)  # vehicle -> [[lat, lon], ...] (experiment.json)
    record_count: int = 0  # records drawn so far (a "pos" frame holds many)
    speedup: float | None = None  # an experiment's (experiment.json): the timeline runs on the wall clock
    span: tuple[float, float] | None = None  # the t_s of the records kept, first to last
    _tails: dict[Path, _Tail] = field(default_factory=dict)
    _seen_kinds: set = field(default_factory=set)
    _pending: bool = False  # a file had more than MAX_READ_BYTES to read

    def __post_init__(self):
        self.run_dir = None if self.run_dir is None else Path(self.run_dir)

    def poll(self) -> list[dict]:
        """The frames appended since the last call (new files are picked up as they appear)."""
        with _collector_paused():
            return self._poll()

    def _poll(self) -> list[dict]:
        self._discover()
        new: list[dict] = []
        read: list[tuple[Path, int, str, str, dict]] = []  # (file, line, source, vehicle, record)
        self._pending = False
        for path, tail in self._tails.items():
            source, vehicle = SOURCES.get(path.name, ""), path.parent.name
            for line_no, line in tail.new_lines():
                try:
                    record = orjson.loads(line)
                except orjson.JSONDecodeError:
                    self._problem(f"{path.relative_to(self.run_dir)}:{line_no}: not a JSON record, skipped")
                    continue
                if not isinstance(record, dict) or not _finite(record.get("t_s")):
                    self._problem(f"{path.relative_to(self.run_dir)}:{line_no}: no t_s, skipped")
                    continue
                read.append((path, line_no, source, vehicle, record))
            for line_no, size in tail.oversized:
                self._problem(f"{path.relative_to(self.run_dir)}:{line_no}: a record of {size:,} bytes, over the "
                              f"{MAX_LINE_BYTES:,}-byte limit, skipped")
            tail.oversized.clear()
            self._pending |= tail.pending
        if self.span is None and read:  # the run's time: where most of its first records are
            middle = statistics.median_low(float(r[4]["t_s"]) for r in read)
            if middle <= time.time() + MAX_GAP_S:
                self.span = (middle, middle)
        telemetry: dict[str, list[dict]] = {}  # vehicle -> its positions in this read, drawn together below
        for path, line_no, source, vehicle, record in read:
            why = self._out_of_span(float(record["t_s"]))
            if why:
                self._problem(f"{path.relative_to(self.run_dir)}:{line_no}: t_s {record['t_s']!r} {why}, skipped")
            elif source == "agent" and record.get("kind") == TELEMETRY:
                telemetry.setdefault(vehicle, []).append(record)
            else:
                self._keep(self._frame(source, vehicle, record), new)
        batches = [(vehicle, records[k:k + MAX_FRAME_POSITIONS]) for vehicle, records in telemetry.items()
                   for k in range(0, len(records), MAX_FRAME_POSITIONS)]
        for frame in self._position_frames(batches):
            self._keep(frame, new)
        return new

    def _out_of_span(self, t_s: float) -> str:
        """Why a record's time is not of this run ("" when it is; the span grows to take it)."""
        if t_s > time.time() + MAX_GAP_S:
            return "is more than a day ahead of this machine's clock"
        if self.span is None:
            self.span = (t_s, t_s)
            return ""
        first, last = self.span
        if t_s < first - MAX_GAP_S or t_s > last + MAX_GAP_S:
            return f"is more than a day from the run's other records ({first:.3f} to {last:.3f})"
        if t_s < first or t_s > last:
            self.span = (min(first, t_s), max(last, t_s))
        return ""

    def add(self, source: str, vehicle: str, record: dict) -> dict | None:
        """One record as a file would hold it ("agent" telemetry or events of `vehicle`, "throughput",
        "compute", "network", "experiment"): its frame, appended, or None when it draws nothing. Live sources
        other than files (a MAVLink link, an agent's state feed) come in here too."""
        if not isinstance(record, dict) or not _finite(record.get("t_s")):
            return None
        if self._out_of_span(float(record["t_s"])):
            return None
        if source == "agent" and record.get("kind") == TELEMETRY:
            return next((self._keep(f, []) for f in self._position_frames([(vehicle, [record])])), None)
        return self._keep(self._frame(source, vehicle, record), [])

    def _keep(self, frame: dict | None, new: list[dict]) -> dict | None:
        if frame is not None:
            frame["s"] = len(self.records)
            self.records.append(frame)
            self.record_count += len(frame["t"]) if frame["k"] == "pos" else 1
            new.append(frame)
        return frame

    def finish(self) -> None:
        """After the run: every file read to its end; a last line without its newline will not be completed
        now."""
        self.poll()
        while self._pending:
            self.poll()
        for path, tail in self._tails.items():
            if tail.skipping:
                self._problem(f"{path.relative_to(self.run_dir)}:{tail.line_no + 1}: a record of "
                              f"{tail.skipping:,} bytes, over the {MAX_LINE_BYTES:,}-byte limit, skipped")
                tail.skipping = 0
            elif tail.partial.strip():
                self._problem(f"{path.relative_to(self.run_dir)}:{tail.line_no + 1}: truncated last line, skipped")
                tail.partial = b""

    def missions_m(self) -> dict[str, list]:
        """Each vehicle's mission waypoints in map metres [[east, north], ...] (empty until a position is heard)."""
        if self.origin is None:
            return {}
        out = {}
        for vehicle, points in self.mission_lla.items():
            enu = [lla_to_enu(lat, lon, self.origin.alt_m, self.origin) for lat, lon in points]
            out[vehicle] = [[round(float(p[0]), 2), round(float(p[1]), 2)] for p in enu]
        return out

    def missing(self) -> list[str]:
        wanted = {"pos": f"positions ({kinds.AGENT_LOG.path} telemetry)",
                  "probe": f"throughput probes ({kinds.THROUGHPUT_LOG.name})",
                  "it": f"compute iterations ({kinds.COMPUTE_LOG.name})",
                  "cap": f"link model capacities ({kinds.NETWORK_LOG.name}, SITL)"}
        return [text for kind, text in wanted.items() if kind not in self._seen_kinds]

    def _problem(self, text: str) -> None:
        if len(self.problems) < 200:
            self.problems.append(text)
        elif len(self.problems) == 200:
            self.problems.append("... more problems not listed")

    def _discover(self) -> None:
        if self.run_dir is None or not self.run_dir.is_dir():
            return
        candidates = [kinds.EXPERIMENT_LOG.at(self.run_dir), kinds.NETWORK_LOG.at(self.run_dir),
                      kinds.ENERGY_LOG.at(self.run_dir)]
        for sub in sorted(p for p in self.run_dir.iterdir() if p.is_dir()):
            candidates += [sub / f.name for f in (kinds.AGENT_LOG, kinds.THROUGHPUT_LOG, kinds.COMPUTE_LOG)]
        for path in candidates:
            if path not in self._tails and path.is_file():
                self._tails[path] = _Tail(path)

    def _frame(self, source: str, vehicle: str, r: dict) -> dict | None:
        kind, t_s = r.get("kind"), float(r["t_s"])
        if kind == kinds.SCHEMA.name and r.get("schema_version") not in READABLE_VERSIONS:
            self._problem(f"{vehicle}/{source}: records of schema version {r.get('schema_version')!r}; this NAC "
                          f"reads versions {', '.join(map(str, READABLE_VERSIONS))}: its records may be misread")
            return None
        if source == "agent":
            if kind == kinds.AGENT_STARTED.name:
                self.vehicles.setdefault(vehicle, {})["role"] = _short(r.get("role", "?"))
            if kind in EVENT_KINDS:
                detail = next((r[k] for k in ("peer", "seq", "value", "text") if r.get(k) is not None), "")
                text = f"{vehicle}: {EVENT_KINDS[kind]} {str(detail)[:MAX_TEXT_CHARS]}".strip()
                return {"k": "ev", "t": t_s, "v": vehicle, "text": text}
            return None
        if source == "throughput" and kind == kinds.THROUGHPUT.name:
            end = r.get("end") or {}
            bps = ((end.get("sum_received") or {}).get("bits_per_second")) if isinstance(end, dict) else None
            speedup = r.get("speedup", 1.0)
            ok = _finite(bps) and _finite(speedup) and speedup > 0 and not r.get("error")
            self._seen_kinds.add("probe")
            # bits per simulated second, as the report gives them: a sped-up run's probe counts wall seconds
            return {"k": "probe", "t": t_s, "a": _short(r.get("client")), "b": _short(r.get("server")),
                    "bps": float(bps) / float(speedup) if ok else 0.0, "ok": bool(ok), "d": _num(r.get("distance_m"))}
        if source == "compute" and kind == kinds.ITERATION.name:
            workers = r.get("workers")
            present = workers.get("present") if isinstance(workers, dict) else None
            present = present if isinstance(present, list) else []
            self._seen_kinds.add("it")
            iteration = r.get("iteration")
            sim_s = _num(r.get("duration_sim_s"))  # simulated, as the report's; absent on a vehicle: wall time
            return {"k": "it", "t": t_s, "i": iteration if type(iteration) is int else None,
                    "dur": sim_s if sim_s is not None else _num(r.get("duration_s")), "ts": _num(r.get("start_sim_s")),
                    "cost": _num(r.get("cost")), "n": sum(1 for p in present if p), "of": len(present)}
        if source == "network" and kind == kinds.LINK_RATES.name:
            columns = [r.get(key) for key in ("a", "b", "rate_bps", "distance_m")]
            if not all(isinstance(c, list) for c in columns) or len({len(c) for c in columns}) != 1:
                return None  # one entry per pair in every column, or nothing to draw
            self._seen_kinds.add("cap")
            return {"k": "cap", "t": t_s, "a": [_short(v) for v in columns[0]], "b": [_short(v) for v in columns[1]],
                    "bps": [_num(v) for v in columns[2]], "d": [_num(v) for v in columns[3]]}
        if source == "experiment" and kind == kinds.EXPERIMENT.name:
            speedup = r.get("speedup")
            self.speedup = float(speedup) if _finite(speedup) and 0 < speedup <= 1000 else None
            for vehicle in r.get("vehicles") or []:
                if isinstance(vehicle, dict) and isinstance(vehicle.get("id"), str):
                    self.vehicles.setdefault(_short(vehicle["id"]), {})["role"] = _short(vehicle.get("role", "?"))
            missions = r.get("missions")
            if isinstance(missions, dict):
                self.mission_lla = {_short(v): [p for p in points if isinstance(p, list) and len(p) == 2
                                             and _finite(p[0]) and _finite(p[1])]
                                    for v, points in missions.items() if isinstance(points, list)}
            return None
        if source == "energy" and kind == kinds.ENERGY.name:
            flight, companion = _num(r.get("flight_soc")), _num(r.get("companion_soc"))
            return {"k": "pw", "t": t_s, "v": _short(r.get("vehicle")),
                    "fs": None if flight is None else round(100 * min(max(flight, 0.0), 1.0)),
                    "cs": None if companion is None else round(100 * min(max(companion, 0.0), 1.0))}
        if source == "experiment" and kind == kinds.FAULT.name:
            text = f"fault: {_short(r.get('fault'))} {_short(r.get('state'))} for {_short(r.get('vehicle'))}"
            return {"k": "ev", "t": t_s, "v": _short(r.get("vehicle")), "fault": True, "text": text}
        return None

    def _position_frames(self, batches: list[tuple[str, list[dict]]]) -> list[dict]:
        """A "pos" frame for each (vehicle, telemetry records) batch, t_s already checked: the records with a
        finite latitude, longitude and altitude on the globe, in map metres. Every batch of a read is converted
        together: a live poll's one record per vehicle costs what one vehicle's does."""
        columns = [_position_columns(records) for _, records in batches]

        def joined(key: str) -> np.ndarray:
            return _floats([value for c in columns for value in c[key]])

        lat, lon, alt = joined("lat_deg"), joined("lon_deg"), joined("alt_m")
        with np.errstate(invalid="ignore"):
            placed = np.isfinite(alt) & (np.abs(lat) <= 90.0) & (np.abs(lon) <= 180.0)
        if not placed.any():
            return []
        if self.origin is None:
            first = int(np.argmax(placed))
            rel = [r for _, records in batches for r in records][first].get("rel_alt_m")
            self.origin = Home(float(lat[first]), float(lon[first]),
                               float(alt[first]) - (float(rel) if _finite(rel) else 0.0))
        with np.errstate(invalid="ignore"):
            enu = np.round(lla_to_enu(lat, lon, alt, self.origin), 2)
        drawn = {"t": joined("t_s").tolist(), "e": enu[:, 0].tolist(), "n": enu[:, 1].tolist(),
                 "u": enu[:, 2].tolist(), "hdg": _or_none(np.round(joined("yaw_deg"), 4)),
                 "tb": _or_none(np.round(joined("time_boot_ms") / 1000.0, 3))}
        placed_list = placed.tolist()
        frames, start = [], 0
        for (vehicle, records), c in zip(batches, columns, strict=True):
            end = start + len(records)
            frame = {"k": "pos", "v": vehicle, **{key: values[start:end] for key, values in drawn.items()},
                     "mode": _texts(c["mode"]), "armed": _bools(c["armed"]), "batt": _numbers(c["battery_pct"]),
                     "seq": _numbers(c["mission_seq"]), "tot": _numbers(c["mission_total"])}
            if not all(placed_list[start:end]):
                keep = [k - start for k in range(start, end) if placed_list[k]]
                frame = {key: [values[k] for k in keep] if isinstance(values, list) else values
                         for key, values in frame.items()}
            start = end
            if frame["t"]:
                self._seen_kinds.add("pos")
                self.vehicles.setdefault(vehicle, {"role": "?"})
                frames.append(frame)
        return frames


def positions(frames: list[dict]) -> list[dict]:
    """Every position the "pos" frames hold, one dict each (keys as the columns, plus "v"): what the page draws."""
    out = []
    for frame in frames:
        if frame["k"] == "pos":
            columns = [key for key in frame if key not in ("k", "v", "s")]
            out += [{"v": frame["v"], **dict(zip(columns, row, strict=True))}
                    for row in zip(*(frame[key] for key in columns), strict=True)]
    return out


@contextlib.contextmanager
def _collector_paused():
    """Python's cycle collector off while a batch of records is read: the frames hold no cycles, and a replay's
    hundred thousand new dicts would set it scanning the growing heap again and again (a third of the time it
    takes to open a 10-minute run)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def _short(value) -> str:
    """A name from a record as the page shows it: a string of at most MAX_ID_CHARS characters."""
    return (value if isinstance(value, str) else str(value))[:MAX_ID_CHARS]


def _num(value) -> float | None:
    return round(float(value), 4) if _finite(value) else None


POSITION_KEYS = ("t_s", "lat_deg", "lon_deg", "alt_m", "yaw_deg", "mode", "armed", "battery_pct", "mission_seq",
                 "mission_total", "time_boot_ms")  # what the agent writes in every telemetry record
_position_values = operator.itemgetter(*POSITION_KEYS)


def _position_columns(records: list[dict]) -> dict[str, list]:
    """The fields the page draws, as columns: taken whole from each record when it has them all, as the agent
    writes them, else field by field (None where one is missing)."""
    try:
        rows = list(map(_position_values, records))
    except KeyError:
        rows = [tuple(r.get(key) for key in POSITION_KEYS) for r in records]
    return dict(zip(POSITION_KEYS, map(list, zip(*rows, strict=True)), strict=True))


# Each column is checked in one pass over its types; only an unusual column is walked value by value.
def _numbers(values: list) -> list:
    """Finite numbers as they are, anything else None."""
    if set(map(type, values)) <= {int, type(None)}:
        return values
    return [value if _finite(value) else None for value in values]


def _texts(values: list) -> list:
    """Strings of at most 40 characters (longer ones cut), anything else None."""
    if set(map(type, values)) <= {str, type(None)} and max(map(len, filter(None, values)), default=0) <= 40:
        return values
    return [value[:40] if type(value) is str else None for value in values]


def _bools(values: list) -> list:
    if set(map(type, values)) <= {bool, type(None)}:
        return values
    return [value if type(value) is bool else None for value in values]


def _floats(values: list) -> np.ndarray:
    """JSON values as floats: NaN for anything that is not a finite number (a string, a bool, null)."""
    if set(map(type, values)) <= {float, int}:
        out = np.array(values, dtype=float)
    else:
        out = np.array([value if _finite(value) else math.nan for value in values], dtype=float)
    out[~np.isfinite(out)] = math.nan  # an integer too large for a float
    return out


def _or_none(values: np.ndarray) -> list:
    return [None if value != value else value for value in values.tolist()]
