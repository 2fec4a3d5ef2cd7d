"""One reader for live and replay: the records of a run directory, read as they are appended, each turned into
the small frame the page draws (positions in local metres, probes, iterations, link capacities, events).

    each vehicle's agent log     telemetry and events       -> "pos" (a batch), "ev"
    the master's probes          iperf3-shaped results      -> "probe"
    the MPI job's records        its iterations             -> "it"
    the kernel network's log     the link model's capacities -> "cap"
    the experiment's log         the runner's faults        -> "ev"

(files and kinds as nac_onboard/records names them: docs/records.md)

A "pos" frame holds every position one read of a vehicle's file gave, as columns ("t", "e", "n", "u", "hdg",
"mode", "armed", "batt", "seq", "tot", "tb", one entry per record): a replay's hundred thousand positions are
sixteen frames, read, sent and parsed as arrays instead of one object each.

Live, a file's last line may still be being written: it waits for its newline. A line that is not JSON, or a
record without what it needs, is skipped and named in `problems` (file and line); what no file holds is in
`missing`. Nothing here raises for a damaged run.
"""

from __future__ import annotations

import contextlib
import gc
import math
import operator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

from missions.geo import Home, lla_to_enu
from nac_onboard.records import READABLE_VERSIONS, kinds

EVENT_KINDS = {k.name: text for k, text in (
    (kinds.LINK_LOST, "autopilot link lost"), (kinds.LINK_RESTORED, "autopilot link back"), (kinds.PEER_LOST, "lost"),
    (kinds.PEER_SEEN, "seen"), (kinds.MISSION_ITEM_REACHED, "reached item"), (kinds.LANDED_STATE, "landed state"),
    (kinds.AGENT_STARTED, "agent started"), (kinds.MODE, "mode"), (kinds.STATUSTEXT, "says"))}
MAX_LINE_BYTES = 1 << 20
SOURCES = {kinds.AGENT_LOG.name: "agent", kinds.THROUGHPUT_LOG.name: "throughput", kinds.COMPUTE_LOG.name: "compute",
           kinds.NETWORK_LOG.name: "network", kinds.EXPERIMENT_LOG.name: "experiment"}
TELEMETRY = kinds.TELEMETRY.name


@dataclass
class _Tail:
    """A file read from where the last read stopped, whole lines only."""

    path: Path
    offset: int = 0
    line_no: int = 0
    partial: bytes = b""

    def new_lines(self) -> list[tuple[int, bytes]]:
        try:
            with open(self.path, "rb") as f:
                f.seek(self.offset)
                data = f.read()
        except OSError:
            return []
        self.offset += len(data)
        data = self.partial + data
        lines = data.split(b"\n")
        self.partial = lines.pop()
        if len(self.partial) > MAX_LINE_BYTES:  # not a line being written: a damaged file
            lines.append(self.partial)
            self.partial = b""
        out = []
        for line in lines:
            self.line_no += 1
            if line.strip():
                out.append((self.line_no, line))
        return out


@dataclass
class RunFollower:
    run_dir: Path | None  # None: no files, only what live sources add
    records: list[dict] = field(default_factory=list)  # every frame so far, in arrival order; "s" is its index
    vehicles: dict[str, dict] = field(default_factory=dict)  # id -> {"role": ...}
    problems: list[str] = field(default_factory=list)
    origin: Home | None = None  # the map's (0, 0): the first position heard, at ground level
    mission_lla: dict[str, list] = field(default_factory=dict)  # vehicle -> [[lat, lon], ...] (experiment.json)
    record_count: int = 0  # records drawn so far (a "pos" frame holds many)
    _tails: dict[Path, _Tail] = field(default_factory=dict)
    _seen_kinds: set = field(default_factory=set)

    def __post_init__(self):
        self.run_dir = None if self.run_dir is None else Path(self.run_dir)

    def poll(self) -> list[dict]:
        """The frames appended since the last call (new files are picked up as they appear)."""
        with _collector_paused():
            return self._poll()

    def _poll(self) -> list[dict]:
        self._discover()
        new: list[dict] = []
        telemetry: dict[str, list[dict]] = {}  # vehicle -> its positions in this read, drawn together below
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
                if source == "agent" and record.get("kind") == TELEMETRY:
                    telemetry.setdefault(vehicle, []).append(record)
                else:
                    self._keep(self._frame(source, vehicle, record), new)
        for frame in self._position_frames(list(telemetry.items())):
            self._keep(frame, new)
        return new

    def add(self, source: str, vehicle: str, record: dict) -> dict | None:
        """One record as a file would hold it ("agent" telemetry or events of `vehicle`, "throughput",
        "compute", "network", "experiment"): its frame, appended, or None when it draws nothing. Live sources
        other than files (a MAVLink link, an agent's state feed) come in here too."""
        if not isinstance(record, dict) or not _finite(record.get("t_s")):
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
        """After the run: a last line without its newline will not be completed now."""
        self.poll()
        for path, tail in self._tails.items():
            if tail.partial.strip():
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
        candidates = [kinds.EXPERIMENT_LOG.at(self.run_dir), kinds.NETWORK_LOG.at(self.run_dir)]
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
                self.vehicles.setdefault(vehicle, {})["role"] = r.get("role", "?")
            if kind in EVENT_KINDS:
                detail = next((r[k] for k in ("peer", "seq", "value", "text") if r.get(k) is not None), "")
                return {"k": "ev", "t": t_s, "v": vehicle, "text": f"{vehicle}: {EVENT_KINDS[kind]} {detail}".strip()}
            return None
        if source == "throughput" and kind == kinds.THROUGHPUT.name:
            end = r.get("end") or {}
            bps = ((end.get("sum_received") or {}).get("bits_per_second")) if isinstance(end, dict) else None
            ok = _finite(bps) and not r.get("error")
            self._seen_kinds.add("probe")
            return {"k": "probe", "t": t_s, "a": str(r.get("client")), "b": str(r.get("server")),
                    "bps": float(bps) if ok else 0.0, "ok": bool(ok), "d": _num(r.get("distance_m"))}
        if source == "compute" and kind == kinds.ITERATION.name:
            workers = r.get("workers") or {}
            present = workers.get("present") or []
            self._seen_kinds.add("it")
            return {"k": "it", "t": t_s, "i": r.get("iteration"), "dur": _num(r.get("duration_s")),
                    "cost": _num(r.get("cost")), "n": sum(1 for p in present if p), "of": len(present)}
        if source == "network" and kind == kinds.LINK_RATES.name:
            self._seen_kinds.add("cap")
            return {"k": "cap", "t": t_s, "a": r.get("a"), "b": r.get("b"), "bps": r.get("rate_bps"),
                    "d": r.get("distance_m")}
        if source == "experiment" and kind == kinds.EXPERIMENT.name:
            for vehicle in r.get("vehicles") or []:
                if isinstance(vehicle, dict) and isinstance(vehicle.get("id"), str):
                    self.vehicles.setdefault(vehicle["id"], {})["role"] = str(vehicle.get("role", "?"))
            missions = r.get("missions")
            if isinstance(missions, dict):
                self.mission_lla = {str(v): [p for p in points if isinstance(p, list) and len(p) == 2
                                             and _finite(p[0]) and _finite(p[1])]
                                    for v, points in missions.items() if isinstance(points, list)}
            return None
        if source == "experiment" and kind == kinds.FAULT.name:
            return {"k": "ev", "t": t_s, "v": r.get("vehicle"), "fault": True,
                    "text": f"fault: {r.get('fault')} {r.get('state')} for {r.get('vehicle')}"}
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


def _finite(value) -> bool:
    """A JSON number that is finite (not a bool, a string, None, NaN or infinity)."""
    kind = type(value)
    if kind is float:  # the usual case first: a replay asks this a million times
        return value - value == 0.0
    if kind is int:
        return True
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


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
