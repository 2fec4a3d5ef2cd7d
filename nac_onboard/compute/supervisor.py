"""Keeping the fleet's MPI job going through lost and returning companions (issue 29).

MPICH cannot keep a job whole when a companion goes: hydra's mpiexec ends every rank when a proxy's connection
closes or resets (a companion's processes killed, or a rebooted one answering a stale connection), UCX's TCP
transport crashes a sender whose peer reset, and a rank cannot be added to a running job (measured on the kernel
network: docs/compute.md). So the job is kept going by starting it again:
- the master stops at the end of an iteration on SIGTERM (from here, or when its proxy dies), its checkpoint and
  summary written (ended_by "stopped"): the next launch starts at the next iteration, none lost or repeated (a
  master killed outright loses what it did since its last checkpoint, --checkpoint-s);
- a launch that ended without its end is started again with `--resume`, over the workers the master's agent
  hears; one that is not set up (a worker unreachable), or finds no worker, waits longer each time;
- a worker back (heard again after it was out of the job, or its rank failed, or heard with another boot of its
  agent: a reboot) for REJOIN_AFTER_S has the master stopped, and joins at the next start; a worker out of range
  that comes back with the same boot is the running job's to take back (it pings it).
A launch ended by its iterations, its duration or its end is the job's end. Launches, stops and waits are records in
compute/job.jsonl.

The caller owns the processes: `start(workers, resume)` launches mpiexec for those workers (in a session of its
own), `live_workers()` says whom the master's agent hears, with their agents' boots (None when it does not
answer; nac_onboard.node.fleet_mpi.heard_workers), `now_s()` is the run's clock (simulated seconds); `poll()` is
called from the caller's loop.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from nac_onboard.child_process import process_running
from nac_onboard.compute.checkpoint import checkpoint_path, load_checkpoint
from nac_onboard.compute.launch import job_processes, mpi_scratch_files, remove_files
from nac_onboard.errors import BadInput
from nac_onboard.flight_log import JsonlLog
from nac_onboard.records import kinds

log = logging.getLogger(__name__)
# simulated: a returning worker heard this long before the job is stopped for it; longer than the agents' peer
# timeout (3 s), so a worker left out of a start while its agent was still heard is found lost first, not taken back
REJOIN_AFTER_S = 5.0
STOP_WAIT_S = 30.0  # wall: a stopped master's iteration, checkpoint and summary; then it is killed
WAIT_FIRST_S, WAIT_MAX_S = 1.0, 30.0  # simulated: the back-off while no worker is heard
LOOK_EVERY_S = 0.25  # wall: how often the master's agent is asked whom it hears
MAX_FAILED_STARTS = 8  # launches in a row that end without a summary (1+2+4+...+30 s of waits): then given up


@dataclass
class Launch:
    number: int
    workers: tuple[str, ...]
    proc: subprocess.Popen
    why: str
    master_pid: int | None = None  # from its run_started record
    summary: dict | None = None
    unanswering: set[str] = field(default_factory=set)  # its workers unresponsive or failed, and not back
    failed: set[str] = field(default_factory=set)  # its workers whose MPI calls failed: their ranks are gone
    boots: dict[str, str] = field(default_factory=dict)  # each worker's agent boot as first heard in this launch
    # the MPI scratch files its proxies and ranks here hold (launch.py): one killed, or outliving mpiexec, dies
    # without removing its own (two topology files per reboot on the sleep network, 2026-11-28), so the launch's end
    # removes them
    scratch: list[str] | None = None


class JobSupervisor:
    def __init__(self, fleet_workers: list[str], start: Callable[[list[str], bool], subprocess.Popen],
                 live_workers: Callable[[], dict[str, str] | None], out_dir: Path, task: str,
                 now_s: Callable[[], float], rejoin_after_s: float = REJOIN_AFTER_S,
                 scratch_noted: Callable[[list[str]], None] | None = None):
        self.fleet_workers, self.start, self.live_workers = list(fleet_workers), start, live_workers
        self.scratch_noted = scratch_noted  # told each launch's MPI files: whoever cleans up if we are killed
        self.out_dir, self.task, self.now_s, self.rejoin_after_s = Path(out_dir), task, now_s, rejoin_after_s
        self.log = JsonlLog(self.out_dir / kinds.JOB_LOG.name)
        self.launch: Launch | None = None
        self.launches = 0
        self.failed_starts = 0
        self._offset = 0  # how far compute.jsonl has been read
        self._heard_since: dict[str, float] = {}  # returning workers: when the agent was first heard again
        self._stopping: tuple[str, list[str], float] | None = None  # (why, vehicles, wall time) of a stop asked
        self._wait_until_s: float | None = None
        self._wait_s = 0.0
        self._why_next = "start"
        self._next_look = 0.0
        self._exclude: dict[str, str | None] = {}  # the last launch's unanswering workers (boot): not in the next,
        # unless heard since with another boot

    # ---- the caller's side ------------------------------------------------------------------------------------
    def begin(self) -> None:
        """The first launch, over every worker of the fleet."""
        self._launch(self.fleet_workers, "start")

    def poll(self) -> int | None:
        """One look: None while the job goes on (running, or about to start again), else its exit code."""
        launch = self.launch
        if launch is None:
            return self._retry()
        self._read_records(launch)
        if launch.scratch is None and launch.master_pid:  # set up: every rank and proxy has made its files
            launch.scratch = mpi_scratch_files(job_processes(getattr(launch.proc, "args", ())))
            if launch.scratch and self.scratch_noted:
                self.scratch_noted(launch.scratch)
        if launch.proc.poll() is None:
            if launch.master_pid and not process_running(launch.master_pid):  # mpiexec would wait on for the workers
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(launch.proc.pid, signal.SIGTERM)
            elif self._stopping is None:
                self._check_rejoin(launch)
            elif time.monotonic() - self._stopping[2] > STOP_WAIT_S:
                self._kill_master(launch)
            return None
        if launch.master_pid and process_running(launch.master_pid):  # mpiexec gone, the master writing its summary
            if self._stopping is None:
                self._stopping = ("launcher lost", [], time.monotonic())
            elif time.monotonic() - self._stopping[2] > STOP_WAIT_S:
                self._kill_master(launch)
            return None
        self._read_records(launch)
        remove_files(launch.scratch or [])
        code = launch.proc.returncode
        ended_by = launch.summary.get("ended_by") if launch.summary else None
        self.log.write(kinds.JOB_ENDED, launch=launch.number, exit_code=code, ended_by=ended_by,
                       t_sim_s=self.now_s())
        if launch.master_pid is not None:
            self._wait_s = 0.0  # it was set up: the back-off starts over
        if ended_by is not None and ended_by != "stopped":
            return 0
        if launch.master_pid is None and code == 2:  # refused its input: every start would be
            return 2
        # a launch that ends without its summary (never set up, or its master killed) counts against the job
        self.failed_starts = self.failed_starts + 1 if ended_by is None else 0
        if self.failed_starts >= MAX_FAILED_STARTS:
            log.error("the MPI job ended without its summary %d times in a row: given up", self.failed_starts)
            return code or 1
        why = self._stopping[0] if self._stopping else "ended without its summary" if ended_by is None else \
            "stopped"
        rejoining = set(self._stopping[1]) if self._stopping else set()
        self._stopping, self.launch = None, None
        self._why_next = why
        self._exclude = {w: launch.boots.get(w) for w in launch.unanswering - rejoining}
        if launch.master_pid is None:  # never set up: a worker unreachable that its agent's silence will show
            self._wait("the last start was not set up (a worker unreachable?)")
        return self._retry()

    def stop(self) -> None:
        """The run is over: no more starts (the caller has ended the running job, whose end is recorded)."""
        launch = self.launch
        if launch is not None and launch.proc.poll() is not None:
            self._read_records(launch)
            remove_files(launch.scratch or [])
            self.log.write(kinds.JOB_ENDED, launch=launch.number, exit_code=launch.proc.returncode,
                           ended_by=launch.summary.get("ended_by") if launch.summary else None, t_sim_s=self.now_s())
        self.launch = None
        self.log.close()

    # ---- inside --------------------------------------------------------------------------------------------
    def _launch(self, workers: list[str], why: str) -> None:
        resume = checkpoint_path(self.out_dir).exists() and self.launches > 0
        from_iteration = None
        if resume:
            try:
                from_iteration = load_checkpoint(self.out_dir, self.task, arrays=False)[0]
            except BadInput as err:  # a torn or foreign checkpoint: start over rather than not at all
                log.warning("%s: starting the job afresh", err)
                resume = False
        self.launches += 1
        with contextlib.suppress(OSError):
            self._offset = (self.out_dir / kinds.COMPUTE_LOG.name).stat().st_size
        proc = self.start(workers, resume)
        self.launch = Launch(self.launches, tuple(workers), proc, why)
        self.log.write(kinds.JOB_LAUNCHED, launch=self.launches, why=why, workers=list(workers), resume=resume,
                       from_iteration=from_iteration, pid=proc.pid, t_sim_s=self.now_s())

    def _retry(self) -> int | None:
        """Start the job again over the workers heard, or wait (longer each time) until one is."""
        if self._wait_until_s is not None and self.now_s() < self._wait_until_s:
            return None
        heard = self.live_workers()
        # the job's word that a worker stopped answering comes before its agent is lost to the master's agent
        workers = [w for w in self.fleet_workers if (heard is None and w not in self._exclude) or (
            heard is not None and w in heard and (w not in self._exclude or heard[w] != self._exclude[w]))]
        if not workers:
            self._exclude.clear()  # the next try believes the agents alone
            self._wait("no worker heard")
            return None
        self._wait_until_s = None
        self._heard_since.clear()
        self._launch(workers, self._why_next)
        return None

    def _wait(self, why: str) -> None:
        """No start before a back-off, longer each time in a row (simulated seconds)."""
        self._wait_s = min(max(2 * self._wait_s, WAIT_FIRST_S), WAIT_MAX_S)
        self._wait_until_s = self.now_s() + self._wait_s
        self.log.write(kinds.JOB_WAITING, why=why, retry_in_s=self._wait_s, t_sim_s=self.now_s())
        log.warning("%s: the MPI job starts again in %.0f s (simulated)", why, self._wait_s)

    def _read_records(self, launch: Launch) -> None:
        """This launch's new records in compute.jsonl: its master's pid, who stopped answering, its summary."""
        path = self.out_dir / kinds.COMPUTE_LOG.name
        try:
            with open(path, "rb") as f:
                f.seek(self._offset)
                data = f.read()
        except OSError:
            return
        whole = data[:data.rfind(b"\n") + 1]  # a line still being written is read next time
        self._offset += len(whole)
        for line in whole.splitlines():
            try:
                record = json.loads(line)
                kind, vehicle = record.get("kind"), record.get("vehicle")
            except (ValueError, AttributeError):
                continue  # the analysis names a malformed line; here it only cannot change the job's state
            if kind == kinds.RUN_STARTED.name and isinstance(record.get("pid"), int):
                launch.master_pid = record["pid"]
            elif kind in (kinds.WORKER_UNRESPONSIVE.name, kinds.WORKER_LOST.name) and isinstance(vehicle, str):
                launch.unanswering.add(vehicle)
                if kind == kinds.WORKER_LOST.name:
                    launch.failed.add(vehicle)
            elif kind == kinds.WORKER_BACK.name and isinstance(vehicle, str):
                launch.unanswering.discard(vehicle)
            elif kind == kinds.RUN_SUMMARY.name:
                launch.summary = record

    def _check_rejoin(self, launch: Launch) -> None:
        """A worker back, heard for rejoin_after_s without a break: stop the master, so that the next start takes
        it in. Back is a worker out of the job, or whose rank failed, or heard with another boot of its agent than
        this launch first heard (a reboot: its rank went with the old boot; an agent restarted alone costs the job
        one restart). A worker the job has that stopped answering with the same boot (out of range) is the job's
        to take back when it answers its pings."""
        if launch.master_pid is None or time.monotonic() < self._next_look:
            return
        self._next_look = time.monotonic() + LOOK_EVERY_S
        heard = self.live_workers()
        if heard is None:
            return
        now_s = self.now_s()
        for w, boot in heard.items():
            launch.boots.setdefault(w, boot)
        returning = {w for w in heard if w in self.fleet_workers and (
            w not in launch.workers or w in launch.failed or heard[w] != launch.boots.get(w))}
        for w in list(self._heard_since):
            if w not in returning:
                del self._heard_since[w]
        for w in returning:
            self._heard_since.setdefault(w, now_s)
        ready = sorted(w for w, since in self._heard_since.items() if now_s - since >= self.rejoin_after_s)
        if not ready:
            return
        self._stopping = ("rejoin", ready, time.monotonic())
        self._why_next = "rejoin"
        self.log.write(kinds.JOB_STOPPING, launch=launch.number, why="rejoin", vehicles=ready, t_sim_s=now_s)
        with contextlib.suppress(ProcessLookupError):
            os.kill(launch.master_pid, signal.SIGTERM)

    def _kill_master(self, launch: Launch) -> None:
        log.warning("the MPI master (pid %s) did not stop within %.0f s: killed", launch.master_pid, STOP_WAIT_S)
        with contextlib.suppress(ProcessLookupError, TypeError):
            os.kill(launch.master_pid, signal.SIGKILL)

