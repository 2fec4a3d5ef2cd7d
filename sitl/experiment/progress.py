"""The experiment's live display: each vehicle followed over its ground link, the latest compute iteration and
throughput probe read from the tail of their logs, one line per refresh."""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path

from nac_onboard.compute.iteration import iterations_per_min
from nac_onboard.mavlink.client import LinkError, VehicleClient
from nac_onboard.mavlink.dialect import COPTER_MODES, M
from nac_onboard.records import Kind, kinds

MODES = {number: name for name, number in COPTER_MODES.items()}
TAIL_BYTES = 65536


@dataclass
class VehicleProgress:
    vehicle: str
    mode: str = "?"
    armed: bool = False
    rel_alt_m: float = 0.0
    speed_mps: float = 0.0
    item: int = 0
    total: int = 0
    reached: list[int] = field(default_factory=list)
    landed: bool = False
    error: str = ""


def follow(client: VehicleClient, progress: VehicleProgress, stop: threading.Event) -> None:
    """Keep progress up to date from the vehicle's messages until stop is set."""
    wanted = ["HEARTBEAT", "GLOBAL_POSITION_INT", "MISSION_ITEM_REACHED", "MISSION_CURRENT"]
    while not stop.is_set():
        try:
            msg = client.recv(wanted, 0.5)
        except (LinkError, OSError) as err:
            progress.error = str(err)
            return
        if msg is None:
            continue
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            progress.mode = MODES.get(msg.custom_mode, str(msg.custom_mode))
            progress.armed = bool(msg.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED)
        elif kind == "GLOBAL_POSITION_INT":
            progress.rel_alt_m = msg.relative_alt / 1000
            progress.speed_mps = math.hypot(msg.vx, msg.vy) / 100
        elif kind == "MISSION_ITEM_REACHED":
            if msg.seq not in progress.reached:
                progress.reached.append(msg.seq)
        else:
            progress.item = msg.seq


def last_record(path: Path, kind: Kind) -> dict | None:
    """The last complete record of this kind in a JSON Lines log, reading only its tail."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(size - TAIL_BYTES, 0))
            tail = f.read()
    except OSError:
        return None
    return _first_of(reversed(tail.split(b"\n")[1 if size > TAIL_BYTES else 0:]), kind)


def first_record(path: Path, kind: Kind) -> dict | None:
    """The first record of this kind in a JSON Lines log, if it is in the log's head."""
    try:
        with open(path, "rb") as f:
            head = f.read(TAIL_BYTES)
    except OSError:
        return None
    return _first_of(head.split(b"\n"), kind)


def _first_of(lines, kind: Kind) -> dict | None:
    for line in lines:
        try:
            record = json.loads(line)
        except ValueError:  # the line being written, or damage: the reader's problem list has it
            continue
        if isinstance(record, dict) and record.get("kind") == kind.name:
            return record
    return None


def pace_per_min(first: dict | None, last: dict) -> float | None:
    """Iterations per simulated minute from the job's first and latest iteration records (the report's formula)."""
    try:
        return iterations_per_min(last["iteration"] + 1, float(first["start_sim_s"]),
                                  float(last["start_sim_s"]) + float(last["duration_sim_s"]))
    except (KeyError, TypeError, ValueError):  # a job on the wall clock, or records without these fields
        return None


def render_progress(t_s: float, states: list[VehicleProgress], run_dir: Path, master: str) -> str:
    cells = [f"{s.vehicle} {s.mode:<6}{'A' if s.armed else '-'} {s.rel_alt_m:4.1f} m {s.speed_mps:3.1f} m/s "
             f"item {s.item}/{s.total}" for s in states]
    line = f"t={t_s:6.1f}s | " + " | ".join(cells)
    iteration = last_record(kinds.COMPUTE_LOG.at(run_dir), kinds.ITERATION)
    if iteration:
        present = iteration.get("workers", {}).get("present", [])
        pace = pace_per_min(first_record(kinds.COMPUTE_LOG.at(run_dir), kinds.ITERATION), iteration)
        line += f" | it {iteration['iteration'] + 1}" + (f", {pace:.1f}/min" if pace is not None else "")
        line += f" ({sum(present)}/{len(present)} workers)"
        if iteration.get("cost") is not None:
            line += f" cost {iteration['cost']:.4f}"
    probe = last_record(kinds.THROUGHPUT_LOG.at(run_dir, master), kinds.THROUGHPUT)
    if probe:
        if "error" in probe:
            line += f" | {probe.get('server')}: no link"
        else:
            rate = probe["end"]["sum_received"]["bits_per_second"] / probe.get("speedup", 1.0) / 1e6
            distance = probe.get("distance_m")
            line += f" | {probe.get('server')}: {rate:.1f} Mbit/s" + (f" at {distance:.1f} m" if distance else "")
    return line
