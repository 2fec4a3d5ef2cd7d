"""The node commands of `nac-onboard`: doctor, mpi hostfile, mpi run (--keep-going)."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from nac_onboard.agent.config import load_agent_config
from nac_onboard.agent.state_feed import StateFeedError, fetch_state
from nac_onboard.clock import from_env
from nac_onboard.compute.launch import mpiexec_path
from nac_onboard.compute.supervisor import JobSupervisor
from nac_onboard.errors import BadInput, OperationFailed
from nac_onboard.node import doctor, fleet_mpi
from nac_onboard.node.facts import read_facts

DEFAULT_LOG_DIR = "/var/log/nac"


def run_doctor(role: str | None, config_path: str | None, as_json: bool = False, out=None) -> int:
    """Print what this node has; 1 when something its role needs is missing."""
    out = out or sys.stdout
    serial_device, log_dir = None, DEFAULT_LOG_DIR
    if config_path:
        config = load_agent_config(config_path)
        role = role or config.vehicle.role
        log_dir = config.log.dir
        if config.autopilot.uri.startswith("serial:"):
            serial_device = config.autopilot.uri.split(":")[1]
    role = role or "worker"
    facts = read_facts(serial_device, log_dir if Path(log_dir).is_absolute() else Path.cwd() / log_dir)
    findings = doctor.assess(facts, role)
    if as_json:
        print(json.dumps({"role": role, "facts": dataclasses.asdict(facts),
                          "findings": [dataclasses.asdict(f) for f in findings]}, indent=2), file=out)
    else:
        print(doctor.report(facts, role, findings), file=out)
    return 1 if any(f.needed for f in findings) else 0


def job_from_feed(feed: str) -> list[fleet_mpi.Node]:
    """The nodes of a job as the master's agent hears them, after the MPI-build check (exit 2 naming the odd
    node out); notes on the peers left out go to stderr."""
    state = fetch_state(feed)
    workers = [p for p in (state.get("peers") or {}).values() if p.get("host") and not p.get("lost")]
    master_host = address_toward(workers[0]["host"]) if workers else "127.0.0.1"
    nodes, notes = fleet_mpi.job_nodes(state, master_host)
    for note in notes:
        print(f"nac-onboard mpi: {note}", file=sys.stderr)
    fleet_mpi.check_builds(nodes)
    return nodes


def address_toward(host: str) -> str:
    """This machine's address on the route to host (what the workers reach the master by); no packet is sent."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.connect((host, 9))
        except OSError as err:
            raise OperationFailed(f"no route to worker {host}: {err.strerror or err}") from None
        return sock.getsockname()[0]


def write_hostfile(feed: str, path: str | None, out=None) -> int:
    nodes = job_from_feed(feed)
    if path:
        save_hostfile(nodes, path, out)
    else:
        print(fleet_mpi.hostfile_text(nodes), end="", file=out or sys.stdout)
    return 0


def save_hostfile(nodes: list[fleet_mpi.Node], path: str, out=None) -> None:
    try:
        Path(path).write_text(fleet_mpi.hostfile_text(nodes))
    except OSError as err:
        raise OperationFailed(f"cannot write the hostfile {path}: {err.strerror}") from None
    print(f"wrote {path}", file=out or sys.stdout)


def run_job(feed: str, hostfile: str, program: list[str], timeout_s: float | None = None) -> int:
    """`mpiexec -f HOSTFILE -n N PROGRAM...` over the nodes heard, once they all run the same MPI build."""
    if not program:
        raise BadInput("mpi run: give the program after --, e.g. -- nac-onboard compute --task linreg")
    nodes = job_from_feed(feed)  # the feed read and the builds checked once, for the hostfile and the count
    save_hostfile(nodes, hostfile, out=sys.stderr)
    command = [mpiexec_path(), "-f", hostfile, "-n", str(len(nodes)), *program]
    try:
        return subprocess.run(command, timeout=timeout_s).returncode
    except FileNotFoundError:
        raise OperationFailed(f"{command[0]} not found: install MPI (nac-onboard doctor)") from None
    except subprocess.TimeoutExpired:
        raise OperationFailed(f"the MPI job did not end within {timeout_s:g} s") from None


def run_kept_job(feed: str, hostfile: str, program: list[str], timeout_s: float | None = None) -> int:
    """`mpi run --keep-going`: the compute job kept going through lost and returning companions by the job's
    supervisor (nac_onboard/compute/supervisor.py): started again from its checkpoint with the workers the agent
    hears, `--vehicles`, `--fleet-workers` and `--resume` added to the program's arguments (the last given wins).
    A worker whose MPI build is not the master's is left out by name, and the job goes on without it."""
    out, task = _value_of(program, "--out"), _value_of(program, "--task")
    if out is None or task is None:
        raise BadInput("mpi run --keep-going: the program must be `nac-onboard compute` with --task and --out (the "
                       "job's records and checkpoint are read from --out)")
    nodes = job_from_feed(feed)
    master, fleet = nodes[0], [n.id for n in nodes[1:]]

    def start(workers: list[str], resume: bool) -> subprocess.Popen:
        try:
            heard = {n.id: n for n in fleet_mpi.job_nodes(fetch_state(feed), master.host)[0][1:]}
        except (StateFeedError, OperationFailed):
            heard = {n.id: n for n in nodes[1:]}
        chosen = [master]
        for worker in workers:
            node = heard.get(worker)
            if node is not None and node.mpi_build != master.mpi_build:
                print(f"nac-onboard mpi: {worker} ({node.host}) runs MPI build {node.mpi_build!r}, not the master's "
                      f"{master.mpi_build!r}: left out", file=sys.stderr)
            elif node is not None:
                chosen.append(node)
        save_hostfile(chosen, hostfile, out=sys.stderr)
        extra = ["--vehicles", ",".join(n.id for n in chosen), "--fleet-workers", ",".join(fleet)]
        command = [mpiexec_path(), "-disable-auto-cleanup", "-f", hostfile, "-n", str(len(chosen)), *program, *extra,
                   *(["--resume"] if resume else [])]
        try:
            return subprocess.Popen(command, start_new_session=True)
        except FileNotFoundError:
            raise OperationFailed(f"{command[0]} not found: install MPI (nac-onboard doctor)") from None

    os.makedirs(out, exist_ok=True)
    supervisor = JobSupervisor(fleet, start, lambda: fleet_mpi.workers_heard_at(feed, 0.5), Path(out), task,
                               from_env().now_s)
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    supervisor.begin()
    try:
        while (code := supervisor.poll()) is None:
            if deadline is not None and time.monotonic() > deadline:
                raise OperationFailed(f"the MPI job did not end within {timeout_s:g} s")
            time.sleep(0.2)
        return code
    finally:
        launch = supervisor.launch
        if launch is not None and launch.proc.poll() is None:  # interrupted, or out of time: the job ends too
            with contextlib.suppress(ProcessLookupError):
                os.killpg(launch.proc.pid, signal.SIGTERM)
            with contextlib.suppress(subprocess.TimeoutExpired):
                launch.proc.wait(10.0)
        supervisor.stop()


def _value_of(args: list[str], option: str) -> str | None:
    """The last value given to `option` (as `--opt V` or `--opt=V`) in a program's arguments."""
    value = None
    for k, arg in enumerate(args):
        if arg == option and k + 1 < len(args):
            value = args[k + 1]
        elif arg.startswith(option + "="):
            value = arg.split("=", 1)[1]
    return value
