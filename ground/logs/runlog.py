"""A run directory read into flat rows: what every vehicle logged, and what could not be read.

The files and kinds are those of nac_onboard/records (docs/records.md): each vehicle's agent log (positions, role)
and probes, its autopilot logs (positions when the agent logged none) and iperf3's own JSON; the compute job's
records (any folder's); the link shaper's rates (a SITL kernel network); the experiment's settings.

Nothing here raises for damaged or missing data: each problem becomes a sentence in `problems` (a truncated
last line, corrupt tlog bytes) or `missing` (a vehicle without positions, a record kind nobody wrote).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

from ground.logs.autopilot_logs import FlightLogError, reader_for
from nac_onboard.errors import BadInput
from nac_onboard.flight_log import read_jsonl
from nac_onboard.inputs import MAX_LOG_BYTES, read_bounded_text
from nac_onboard.records import kinds

log = logging.getLogger(__name__)


class RunDirError(BadInput):
    """Nothing to analyse: the directory is missing or holds no NAC logs."""


@dataclass
class RunLog:
    path: Path
    vehicles: dict[str, str] = field(default_factory=dict)  # id -> role ("master", "worker", "?")
    positions: list[dict] = field(default_factory=list)
    probes: list[dict] = field(default_factory=list)
    iterations: list[dict] = field(default_factory=list)
    compute_runs: list[dict] = field(default_factory=list)  # run_started records
    compute_ends: list[dict] = field(default_factory=list)  # run_summary records
    link_rates: list[dict] = field(default_factory=list)  # the shaper's link_rates records (SITL, kernel network)
    air_medium: list[dict] = field(default_factory=list)  # the frame-level air's counters (air = "medium")
    experiment: dict | None = None  # the runner's experiment.json, when there is one
    energy: list[dict] = field(default_factory=list)  # the experiment's energy records, a vehicle a second
    energy_plan: dict | None = None  # its energy models
    battery_empty: list[dict] = field(default_factory=list)  # companion packs that ran out
    events: list[dict] = field(default_factory=list)  # faults as they happened, the MPI job's starts and stops
    problems: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return self.path.name

    def master(self, requested: str | None = None) -> str | None:
        """The master's vehicle id: the one asked for (it must be in the run), else the one whose agent logged
        role master, else the client of the throughput probes (the master probes its workers), said as a
        problem; None when nothing tells (the analysis then has no distances and says why)."""
        found = ", ".join(sorted(self.vehicles)) or "none"
        if requested:
            if requested not in self.vehicles:
                raise BadInput(f"{self.name}: --master {requested}: no vehicle of that name in the run "
                               f"(vehicles found: {found})")
            return requested
        masters = sorted(v for v, role in self.vehicles.items() if role == "master")
        if masters:
            return masters[0]
        clients = sorted({p.get("client") for p in self.probes if p.get("client") in self.vehicles})
        if len(clients) == 1:
            _warn(self, [f"{self.name}: no agent logged role master; {clients[0]} taken as the master, as the client "
                         f"of the throughput probes (give --master ID to choose)"])
            return clients[0]
        return None


def _warn(run: RunLog, problems: list[str]) -> None:
    for problem in problems:
        log.warning("%s", problem)
        run.problems.append(problem)


def read_run(path: str | Path) -> RunLog:
    path = Path(path)
    if not path.is_dir():
        raise RunDirError(f"{path}: no such run directory")
    run = RunLog(path)
    experiment = kinds.EXPERIMENT_LOG.at(path)
    if experiment.exists():
        read = read_jsonl(experiment)
        _warn(run, read.problems)
        run.experiment = {}
        for record in read.records:  # the runner's start record, then its end record (outcome)
            if record.get("kind") != kinds.FAULT.name:  # each fault as it happened; the end record lists them all
                run.experiment.update(record)
            elif isinstance(record.get("t_s"), (int, float)):
                run.events.append({"t_s": float(record["t_s"]),
                                   "what": f"{record.get('fault')} {record.get('state')}: {record.get('vehicle')}"})
    network = kinds.NETWORK_LOG.at(path)
    if network.exists():
        read = read_jsonl(network)
        _warn(run, read.problems)
        run.link_rates = read.of_kind(kinds.LINK_RATES)
        run.air_medium = read.of_kind(kinds.AIR_MEDIUM)
    energy = kinds.ENERGY_LOG.at(path)
    if energy.exists():
        read = read_jsonl(energy)
        _warn(run, read.problems)
        run.energy, run.battery_empty = read.of_kind(kinds.ENERGY), read.of_kind(kinds.BATTERY_EMPTY)
        run.energy_plan = next(iter(read.of_kind(kinds.ENERGY_PLAN)), None)
    for vehicle_dir in sorted(p for p in path.iterdir() if p.is_dir()):
        _read_vehicle(run, vehicle_dir)
    for compute_log in sorted(path.rglob(kinds.COMPUTE_LOG.name)):
        read = read_jsonl(compute_log)
        _warn(run, read.problems)
        run.compute_runs += read.of_kind(kinds.RUN_STARTED)
        run.compute_ends += read.of_kind(kinds.RUN_SUMMARY)
        run.iterations += read.of_kind(kinds.ITERATION)
    for job_log in sorted(path.rglob(kinds.JOB_LOG.name)):
        read = read_jsonl(job_log)
        _warn(run, read.problems)
        for r in read.of_kind(kinds.JOB_LAUNCHED, kinds.JOB_STOPPING):
            if r["kind"] == kinds.JOB_LAUNCHED.name and r.get("launch") == 1:
                continue
            what = f"job started again ({r.get('why')})" if r["kind"] == kinds.JOB_LAUNCHED.name else \
                f"job stopped ({r.get('why')})"
            run.events.append({"t_s": float(r["t_s"]), "what": what})
    run.events.sort(key=lambda e: e["t_s"])
    _check_clocks(run)
    if not run.vehicles and not run.iterations:
        raise RunDirError(f"{path}: no NAC logs here (expected {kinds.AGENT_LOG.path}, autopilot logs or "
                          f"{kinds.COMPUTE_LOG.path}); is this a run directory?")
    for vehicle in run.vehicles:
        if not any(p["vehicle"] == vehicle for p in run.positions):
            run.missing.append(f"vehicle {vehicle}: no positions (no telemetry records and no autopilot log)")
    if not run.probes and not probes_off(run.experiment):
        run.missing.append(f"throughput: no probe records ({kinds.THROUGHPUT_LOG.name})")
    if not run.iterations:
        run.missing.append(f"compute: no iteration records ({kinds.COMPUTE_LOG.name})")
    return run


def _check_clocks(run: RunLog) -> None:
    """Distances pair vehicles by time: a log without GPS time (seconds since boot) cannot be paired with unix
    times, and two boot clocks only if the vehicles booted together. Say so instead of leaving tables empty."""
    bases: dict[str, set[str]] = {}
    for row in run.positions:
        bases.setdefault(row["vehicle"], set()).add(row.get("time_base", "unix"))
    on_boot = sorted(v for v, b in bases.items() if "boot" in b)
    if on_boot and len(on_boot) < len(bases):
        _warn(run, [f"{', '.join(on_boot)}: positions on seconds since boot (no GPS time in the log), the others on "
                    f"unix time: they cannot be paired, so there are no distances to {', '.join(on_boot)}"])
    elif len(on_boot) > 1:
        _warn(run, [f"{', '.join(on_boot)}: every log is on seconds since boot (no GPS time): distances pair them "
                    f"as if the vehicles had booted at the same moment"])


def _read_vehicle(run: RunLog, vehicle_dir: Path) -> None:
    vehicle = vehicle_dir.name
    agent_log = vehicle_dir / kinds.AGENT_LOG.name
    flight_logs = sorted(p for p in vehicle_dir.iterdir() if reader_for(p))
    iperf3_files = sorted(vehicle_dir.glob(IPERF3_GLOB))
    if not agent_log.exists() and not flight_logs and not iperf3_files:
        return
    role = "?"
    telemetry = 0
    tlog_simulated = False
    if agent_log.exists():
        read = read_jsonl(agent_log)
        _warn(run, read.problems)
        for r in read.records:
            kind = r["kind"]
            if kind == kinds.TELEMETRY.name:
                telemetry += 1
                run.positions.append({"vehicle": vehicle, "source": "agent", "t_s": r["t_s"],
                                      "time_boot_ms": r.get("time_boot_ms"), "lat_deg": r.get("lat_deg"),
                                      "lon_deg": r.get("lon_deg"), "alt_m": r.get("alt_m"),
                                      "rel_alt_m": r.get("rel_alt_m"), "armed": r.get("armed"),
                                      "mission_seq": r.get("mission_seq")})
            elif kind == kinds.AGENT_STARTED.name:
                role = r.get("role", role)
                tlog_simulated = r.get("tlog_clock") == "simulated"
    run.vehicles[vehicle] = role
    if telemetry == 0:
        if tlog_simulated:  # its stamps run at the simulator's pace, the other records' at the wall clock's
            _warn(run, [f"{vehicle}/{kinds.TLOG.name}: on the simulated clock of a sped-up run, not used for "
                        "positions (they would not line up with the probes and iterations)"])
            flight_logs = [p for p in flight_logs if p.name != kinds.TLOG.name]
        for flight_log in flight_logs:  # the autopilot's own record when the agent logged no positions
            try:
                rows, problems = reader_for(flight_log)(flight_log, vehicle)
            except FlightLogError as err:
                rows, problems = [], [str(err)]
            _warn(run, problems)
            run.positions += rows
            if rows:
                break
    for path in iperf3_files:
        probes, problems = iperf3_probes(path, vehicle)
        _warn(run, problems)
        run.probes += probes
    throughput_log = vehicle_dir / kinds.THROUGHPUT_LOG.name
    if throughput_log.exists():
        read = read_jsonl(throughput_log)
        _warn(run, read.problems)
        run.probes += read.of_kind(kinds.THROUGHPUT)


IPERF3_GLOB = kinds.IPERF3_GLOB


def _json_documents(text: str) -> tuple[list, str | None]:
    """Every JSON value in the text, one after another (iperf3 --json >> file appends one per test), up to the
    first that does not parse, and what is wrong with that one."""
    decoder, found, at = json.JSONDecoder(), [], 0
    while True:
        while at < len(text) and text[at] in " \t\r\n":
            at += 1
        if at == len(text):
            return found, None
        try:
            value, at = decoder.raw_decode(text, at)
        except (ValueError, RecursionError) as err:
            return found, f"result {len(found) + 1}: {err}"
        found.append(value)


def iperf3_probes(path: Path, client: str) -> tuple[list[dict], list[str]]:
    """Probe records from iperf3's own JSON output, one per test the file holds (a flight script's `>>` appends
    them; the run's time from each start.timestamp, the distance later from the two vehicles' positions), and the
    problems of what is skipped: a damaged result ends the file, the ones before it are kept."""
    server = path.name[len("iperf3-"):].split(".")[0]
    expected = "expected the output of `iperf3 --client PEER --json`"
    try:
        documents, damaged = _json_documents(read_bounded_text(path, "iperf3 JSON", MAX_LOG_BYTES))
    except BadInput as err:
        return [], [f"{path}: not iperf3 JSON ({expected}): {err}"]
    probes, problems = [], []
    for k, data in enumerate(documents, 1):
        where = f"{path}" if len(documents) == 1 and not damaged else f"{path}: result {k}"
        probe, problem = _iperf3_probe(data, where, client, server)
        if problem:
            problems.append(problem)
        else:
            probes.append(probe)
    if damaged or not documents:
        problems.append(f"{path}: not iperf3 JSON ({expected}): {damaged or 'empty'}")
    return probes, problems


def _iperf3_probe(data, where: str, client: str, server: str) -> tuple[dict | None, str | None]:
    start = data.get("start") if isinstance(data, dict) else None
    timesecs = (start or {}).get("timestamp", {}).get("timesecs") if isinstance(start, dict) else None
    if not isinstance(timesecs, (int, float)) or not server:
        return None, (f"{where}: iperf3 JSON without start.timestamp.timesecs (a test that never connected?) or "
                      "without a peer in its name (iperf3-PEER.json): skipped")
    record = {"kind": kinds.THROUGHPUT.name, "t_s": float(timesecs), "client": client, "server": server,
              "start": start, "end": data.get("end") or {}, "source": where}
    received = (record["end"].get("sum_received") or {}).get("bits_per_second") if isinstance(
        record["end"], dict) else None
    if data.get("error") or not isinstance(received, (int, float)):
        record["error"] = str(data.get("error") or "iperf3 reported no received total")
    return record, None


def probes_off(experiment: dict | None) -> bool:
    """Whether the run's experiment ran no probes by its scenario (its record says so): then a run without probe
    records lacks nothing."""
    return experiment is not None and "probes" in experiment and not experiment["probes"]
