"""Networked airborne computing over MPI (DESIGN.md 5, Algorithm 1): rank 0 is the master, ranks 1..N workers.

    mpiexec -n N+1 -bind-to core python -m mpi4py -m nac_onboard.compute --task matmul|linreg [options]

Each iteration the master sends every worker in range its input (B for matmul, the weights for linreg), waits for
the results until --timeout-s, and combines what arrived. The task (task.py) gives only the input, the work, the
combination and what to send again for blocks that did not arrive; this module does all the sending, waiting and
bookkeeping. With --emulate sleep (the research's method) the master sleeps I/C before each send and tells the
worker the link's capacity C, so the worker sleeps before its answer too; C comes from the channel model at the two
vehicles' distance, and below the model's minimum rate the worker is out of range: nothing is sent. A worker that
misses an iteration is absent for it (linreg carries on with the gradients that arrived, weighted by shard size;
matmul re-assigns the missing rows to live workers or marks the iteration incomplete, --on-missing) and takes part
again as soon as it answers. A worker that misses UNRESPONSIVE_AFTER iterations in a row (out of range, stopped, or
dead) is no longer waited for and is pinged until it answers; a worker process that dies leaves the others training
(MPI errors are returned, not fatal, and sends give up at their deadline; launch.py starts the job so that hydra
does not kill the rest). A master that raises aborts the job (exit code != 0): its records, one line each, and its
last checkpoint are on disk by then.

Records (JSON Lines, --out DIR/compute.jsonl): run_started, one `iteration` record per iteration, run_summary.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import signal
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from nac_onboard.child_process import die_with_parent
from nac_onboard.compute.allocation import Planner
from nac_onboard.compute.checkpoint import checkpoint_path, load_checkpoint
from nac_onboard.compute.device import CpuStretch
from nac_onboard.compute.iteration import IterationLinks
from nac_onboard.compute.mailbox import Inbox, wait_for
from nac_onboard.compute.messages import (
    BITS_PER_FLOAT,
    KIND_EXTRA,
    KIND_PLAN,
    KIND_STOP,
    KIND_WARMUP,
    KIND_WORK,
    RESULT_BATCH,
    RESULT_COMPUTE_S,
    RESULT_HEADER,
    RESULT_ITERATION,
    RESULT_LATE,
    RESULT_LATE_S,
    RESULT_MORE,
    RESULT_ROWS,
    RESULT_SSE,
    RESULT_UP_S,
    STOPPED_ANSWER,
    TAG_RESULT,
    TAG_WORK,
    WARMUP_ANSWER,
    WORK_EXTRA_ROWS,
    WORK_HEADER,
    WORK_KIND,
    pad_floats,
    work_header,
)
from nac_onboard.compute.messages import message as message_buffer
from nac_onboard.compute.options import ComputeOptions, build_source, parse_args
from nac_onboard.compute.task import Answer, Extra, Task
from nac_onboard.errors import NacError
from nac_onboard.flight_log import JsonlLog
from nac_onboard.link.emulation import SleepEmulation
from nac_onboard.radio.transfers import LinkNow, backlog_drain_s
from nac_onboard.records import kinds

IDLE_FIRST_S, IDLE_MAX_S = 0.05, 1.0  # simulated seconds: the back-off while no worker is in range
UNRESPONSIVE_AFTER = 3  # iterations missed in a row before a worker is no longer waited for
PING_S = 1.0  # how often an unresponsive worker is asked whether it is back
DISK_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)  # a checkpoint that fails with these is skipped, not fatal


# ---- workers ---------------------------------------------------------------------------------------------------
def run_worker(comm, mpi, options: ComputeOptions, log: JsonlLog) -> bool:
    """Answers the master until its STOP; returns whether MPI_Finalize may run (no rank was lost)."""
    rank = comm.Get_rank()
    bounds = comm.bcast(None, root=0)
    task = options.task_class(options)
    take_block(task, rank, bounds, log)
    pad = pad_floats(options.pad_bits)
    inbox = Inbox(comm, mpi, [0], TAG_WORK, WORK_HEADER + max(task.largest_input(), 2 * len(bounds)), pad)
    emulation = SleepEmulation(options.channel, options.clock)
    stretch = CpuStretch(options.device_for(rank).slowdown, options.clock)
    warmup_answer = message_buffer(WARMUP_ANSWER, 0, pad)
    answers = {}  # reused answer buffers by result size: no allocation per iteration
    early = None  # a message that came while a batched answer was still being worked on

    def answer(buf: np.ndarray) -> None:
        """buf to the master, or left behind if a STOP that does not finalize came first (the loop takes it next)."""
        deadline = time.monotonic() + options.clock.wall_s(options.idle_timeout_s)
        if send_to_master(comm, mpi, inbox, buf, deadline) is None:
            give_up(rank, options, log, "the master took no answer")

    while True:
        if early is not None:
            message, early = early, None
        else:
            _, message = inbox.receive(time.monotonic() + options.clock.wall_s(options.idle_timeout_s))
        if message is None:
            give_up(rank, options, log, "nothing from the master")
        kind, iteration, rate_bps, extra_rows, loss, phy_bps = message[:WORK_HEADER].tolist()  # floats: cheap tests
        if kind == KIND_STOP:  # the master drains everything up to STOPPED_ANSWER, for --timeout-s, to finalize
            finalizes = extra_rows == 0 and bool(send_to_master(
                comm, mpi, inbox, message_buffer(STOPPED_ANSWER, 0, pad),
                time.monotonic() + options.clock.wall_s(options.timeout_s)))
            inbox.close()
            return finalizes
        if kind == KIND_WARMUP:
            answer(warmup_answer)
            continue
        if kind == KIND_PLAN:
            take_block(task, rank, plan_of(message[WORK_HEADER:]), log)
            continue
        extra = int(extra_rows) if kind == KIND_EXTRA else None
        batches = 1 if extra is not None else task.batches()
        for batch in range(batches):
            if batch:  # the next iteration's input already here: this one is decoded, the rest is not needed
                early = inbox.receive(time.monotonic())[1]
                if early is not None:
                    break
            t0 = time.perf_counter()
            stretch.begin()
            result, rows, sse = task.work(message[WORK_HEADER:], extra) if batches == 1 else \
                task.work_batch(message[WORK_HEADER:], batch)
            compute_s = stretch.hold() if stretch.active else time.perf_counter() - t0
            up_s = emulation.delay(result.size * BITS_PER_FLOAT, rate_bps, loss, phy_bps)
            buf = answers.get(result.size)
            if buf is None:
                buf = answers[result.size] = message_buffer((), RESULT_HEADER + result.size, pad)
            buf[:RESULT_HEADER] = (iteration, compute_s, up_s, rows, sse, stretch.late, batch, batch < batches - 1,
                                   stretch.late_s)
            buf[RESULT_HEADER:RESULT_HEADER + result.size] = result
            answer(buf)


def send_to_master(comm, mpi, inbox: Inbox, buf: np.ndarray, deadline: float) -> bool | None:
    """Send buf to the master, taking what comes from it meanwhile (mailbox.py: a blocked send waited forever for a
    master that had stopped reading). True once sent; False as soon as a STOP that does not finalize is in (the master
    will take nothing more: the send is left behind, and the rank ends without MPI_Finalize); None at the deadline."""
    def a_stop_without_finalize_came() -> bool:
        inbox.take_ready()
        return any(m[WORK_KIND] == KIND_STOP and m[WORK_EXTRA_ROWS] != 0 for _, m in inbox.taken)

    return wait_for(comm.Isend([buf, mpi.DOUBLE], dest=0, tag=TAG_RESULT).Test, deadline, a_stop_without_finalize_came)


def give_up(rank: int, options: ComputeOptions, log: JsonlLog, why: str) -> None:
    """End this worker (exit 3) after --idle-timeout-s without the master."""
    log.write(kinds.WORKER_GAVE_UP, rank=rank, idle_timeout_s=options.idle_timeout_s)
    log.close()
    sys.stderr.write(f"worker {rank}: {why} for {options.idle_timeout_s:g} s; giving up (exit 3)\n")
    # each worker gives up by its own timeout; MPI_Abort would kill its hydra proxy with it, which then
    # leaves its hwloc file in /tmp (hard-coded in hydra_pmi_proxy: 2 a killed-master run, measured)
    end_without_finalize(3)


def take_block(task: Task, rank: int, bounds: list[tuple[int, int]], log: JsonlLog) -> None:
    """Split and take this worker's block (at the start and at each re-plan), its cost in the rank's log: for a
    coded task, the encoding of its coded block or units."""
    t0 = time.perf_counter()
    task.split(bounds)
    task.take_block(rank)
    log.write(kinds.BLOCK_TAKEN, rank=rank, block=list(bounds[rank - 1]), take_s=time.perf_counter() - t0)


def plan_of(payload: np.ndarray) -> list[tuple[int, int]]:
    """Every worker's [start, stop) from a KIND_PLAN payload."""
    flat = payload.astype(int).tolist()
    return list(zip(flat[0::2], flat[1::2], strict=True))


# ---- master ----------------------------------------------------------------------------------------------------
@dataclass
class Tally:
    """What the run summary adds up over the iterations."""

    absences: dict[int, int]  # rank -> iterations absent
    durations: list[float] = field(default_factory=list)
    complete: int = 0


class Master:
    def __init__(self, comm, mpi, options: ComputeOptions, log: JsonlLog):
        self.comm, self.mpi, self.options, self.log = comm, mpi, options, log
        self.workers = list(range(1, comm.Get_size()))
        self.vehicles = [options.vehicle_of(rank) for rank in self.workers]
        self.source = build_source(options)
        self.clock = options.clock
        self.pad = pad_floats(options.pad_bits)
        self.emulation = SleepEmulation(options.channel, self.clock) if options.emulate == "sleep" else None
        self.task: Task = options.task_class(options)
        self.planner = Planner(options, self.workers, self.task, self.source)
        self.stretch = CpuStretch(options.device_for(0).slowdown, self.clock)
        self.late_by_worker: dict[int, tuple[int, float]] = {}  # rank -> its late work segments so far and by how
        # much in all (simulated seconds), as its last answer said
        self.bounds: list[tuple[int, int]] = []
        self.stale_results = 0
        self.inbox: Inbox | None = None  # posted once the shards are known
        self.pending: tuple | None = None  # the last iteration, not yet tallied and written
        self.tally = Tally({r: 0 for r in self.workers})
        self.unresponsive: set[int] = set()
        self._missed: dict[int, int] = {}
        self._next_ping_s: dict[int, float] = {}
        self._pings: dict[int, tuple] = {}  # rank -> (request, buffer) of the ping in flight
        self._stuck: list[tuple] = []  # (rank, request, buffer) of sends that missed their deadline
        self.lost: dict[int, str] = {}  # rank -> the MPI error that ended communication with it
        self.undrained: set[int] = set()  # ranks whose STOPPED_ANSWER did not come: MPI_Finalize would fail
        self._stalled_s = 0.0  # wall seconds this iteration spent on sends that missed their deadline
        self._next_checkpoint_s = 0.0
        self.stop_signal: str | None = None  # set by request_stop
        self.agents_lost: set[int] = set()  # workers whose agents the master's agent lost or heard restarted, now
        self.checkpoint_iteration: int | None = None  # the iteration of the last whole checkpoint on disk
        self.end_at_s = options.end_at_s

    def link(self, distances: dict) -> IterationLinks:
        """Per worker: distance, emulated rate and whether it is in range this iteration."""
        links = IterationLinks(len(self.workers))
        self.agents_lost = lost = self.source.lost_ranks() if self.source is not None else set()
        for k, rank in enumerate(self.workers):
            d = distances.get(rank) if distances else None
            links.distance_m[k] = d
            if rank in self.unresponsive:
                links.absent[k] = "unresponsive"  # not waited for; pinged until it answers again
            elif rank in lost:
                links.absent[k] = "agent_lost"  # its agent unheard (the fleet's Wi-Fi): nothing of it is believed
            elif self.emulation is not None:
                if d is None:
                    links.absent[k] = "no_position"
                else:
                    now = self.emulation.link(d, rank, (self.options.vehicle_of(0), self.options.vehicle_of(rank)))
                    links.rate_bps[k], links.loss[k], links.phy_bps[k] = now.capacity_bps, now.loss, now.phy_bps
                    if not now.in_range:
                        links.absent[k] = "out_of_range"
        return links

    def replan(self, iteration: int, distances: dict, links: IterationLinks) -> None:
        """--replan-every: new blocks every N iterations, and at once when a worker is absent or unresponsive
        (planned out) or back; KIND_PLAN to every worker MPI has not lost, before this iteration's inputs (MPI keeps
        a sender's order, so each worker works on the new blocks from this iteration on)."""
        why = self.planner.why_now(iteration, links)
        if why is None:
            return
        shares, bounds = self.planner.blocks(distances, self.bounds, self.planner.planned_out)
        if bounds == self.bounds:
            return
        self.bounds = bounds
        self.task.split(bounds)
        payload = np.array([x for block in bounds for x in block], dtype=float)
        message = message_buffer(work_header(KIND_PLAN, iteration), payload.size, self.pad)
        message[WORK_HEADER:WORK_HEADER + payload.size] = payload
        timeout_s = self.clock.wall_s(self.options.timeout_s)
        for rank in self.workers:
            if rank not in self.lost and not self._send_within(rank, message, timeout_s):
                message = message.copy()
            links.bytes_down[rank - 1] += message.nbytes
        self.log.write(kinds.BLOCKS_PLANNED, iteration=iteration, why=why, shares=shares, bounds=bounds,
                       planned_out=sorted(self.planner.planned_out), rates_bps=self.planner.rates_bps,
                       link_rates=self.options.link_rates)

    def send(self, rank: int, kind: float, iteration: int, payload: np.ndarray, links: IterationLinks,
             extra_rows: int = 0, message: np.ndarray | None = None) -> np.ndarray:
        """Send one input; `message` is a reusable buffer whose payload part is already filled. Returns the buffer
        the next send may fill (a copy, if a send that missed its deadline still holds this one)."""
        k = rank - 1
        rate, loss, phy = links.rate_bps[k] or 0.0, links.loss[k] or 0.0, links.phy_bps[k]
        # the research's emulation: the transfer takes I/C before it happens
        down_s = self.emulation.delay(payload.size * BITS_PER_FLOAT, rate, loss, phy) if self.emulation else 0.0
        if message is None:
            message = message_buffer((), WORK_HEADER + payload.size, self.pad)
            message[WORK_HEADER:WORK_HEADER + payload.size] = payload
        message[:WORK_HEADER] = work_header(kind, iteration, rate, extra_rows, loss, phy)
        sent = self._send_within(rank, message, self.clock.wall_s(self.options.timeout_s))
        links.bytes_down[k] += message.nbytes
        links.down_s[k] += down_s
        return message if sent else message.copy()

    def _send_within(self, rank: int, message: np.ndarray, timeout_s: float) -> bool:
        """A send that gives up after timeout_s (wall): a large input waits for its receiver, which a dead or
        stopped worker never is. A request left behind is kept (with its buffer) until MPI completes or fails it."""
        request = self._isend(rank, message)
        if request is None or self._test(rank, request):  # the usual case: a small message goes at once
            return True
        t0 = time.monotonic()
        meanwhile = None if self.inbox is None else self.inbox.take_ready  # this worker's answer may wait (mailbox.py)
        if wait_for(lambda: self._test(rank, request), t0 + timeout_s, meanwhile):
            return True
        self._stuck.append((rank, request, message))
        self._stalled_s += time.monotonic() - t0
        return False

    def _isend(self, rank: int, message: np.ndarray):
        """The request of a posted send, or None if MPI failed it at once (the rank is then lost)."""
        try:
            return self.comm.Isend([message, self.mpi.DOUBLE], dest=rank, tag=TAG_WORK)
        except self.mpi.Exception as err:
            self._lose(rank, str(err))
            return None

    def _test(self, rank: int, request) -> bool:
        """Whether a request is over; an MPI error on it (errors are returned, not fatal) loses the rank."""
        try:
            return request.Test()
        except self.mpi.Exception as err:
            self._lose(rank, str(err))
            return True

    def _lose(self, rank: int, error: str) -> None:
        if rank not in self.lost:
            self.lost[rank] = error
            self.log.write(kinds.WORKER_LOST, rank=rank, vehicle=self.options.vehicle_of(rank), error=error)
        if rank not in self.unresponsive:
            self.unresponsive.add(rank)
            self._next_ping_s[rank] = float("inf")  # MPI said it is gone: nothing to ping

    def refuse(self, rank: int, why: str) -> None:
        """A worker that would compute another problem (another data set, another task): it has ended itself (exit
        2); the job goes on without it, never sending to it."""
        self.lost[rank] = why
        self.unresponsive.add(rank)
        self._next_ping_s[rank] = float("inf")
        self.log.write(kinds.WORKER_REFUSED, rank=rank, vehicle=self.options.vehicle_of(rank), why=why)

    def _reap(self) -> None:
        """Forget the sends that missed their deadline and have since completed or failed; note failed receives."""
        self._stuck = [item for item in self._stuck if not self._test(item[0], item[1])]
        for rank, error in self.inbox.failed.items():
            self._lose(rank, error)
        self.inbox.failed.clear()

    def _note_answers(self, iteration: int, waited: set[int], answered: set[int]) -> None:
        """A worker that misses UNRESPONSIVE_AFTER iterations in a row (a dead or stopped process, which MPI may
        not report) is no longer waited for: each of its misses would cost the whole timeout."""
        for rank in answered:
            self._missed[rank] = 0
        for rank in waited - answered:
            self._missed[rank] = self._missed.get(rank, 0) + 1
            if self._missed[rank] >= UNRESPONSIVE_AFTER and rank not in self.unresponsive:
                self.unresponsive.add(rank)
                self._next_ping_s[rank] = 0.0
                self.log.write(kinds.WORKER_UNRESPONSIVE, rank=rank, vehicle=self.options.vehicle_of(rank),
                               iteration=iteration, missed=self._missed[rank])

    def _ping_unresponsive(self) -> None:
        """A small non-blocking message to each unresponsive worker every PING_S: its answer brings it back."""
        now = time.monotonic()
        for rank in sorted(self.unresponsive):
            pending = self._pings.get(rank)
            if now < self._next_ping_s.get(rank, 0.0) or (pending is not None and not self._test(rank, pending[0])):
                continue
            message = message_buffer(work_header(KIND_WARMUP), 0, self.pad)
            request = self._isend(rank, message)
            if request is not None:
                self._pings[rank] = (request, message)
            self._next_ping_s[rank] = now + self.clock.wall_s(PING_S)

    def _hear_until(self, deadline: float) -> None:
        """The inbox while no worker is waited for, until one is back or the deadline: with every worker
        unresponsive, nothing else reads the answers to the pings that bring them back."""
        while True:
            rank, buf = self.inbox.receive(deadline)
            if buf is None:
                return
            self.stale_results += 1  # a ping's answer, or a result whose iteration was closed
            if rank in self.unresponsive:
                self._back(rank)
                return

    def _back(self, rank: int) -> None:
        self.unresponsive.discard(rank)
        self._missed[rank] = 0
        self.log.write(kinds.WORKER_BACK, rank=rank, vehicle=self.options.vehicle_of(rank))

    def probes_queue_s(self, links: IterationLinks) -> float | None:
        """--probe-backlog-packets: how long this round's inputs wait in the master's transmit queue behind the
        packets the probes alongside keep there, shared among the links in range (simulated seconds; None: no such
        queue is modelled). The round's inputs go into the queue together, so they wait for it once."""
        if not self.options.probe_backlog_packets or self.emulation is None:
            return None
        probed = [LinkNow(links.distance_m[k] or 0.0, links.rate_bps[k] or 0.0, True, links.loss[k] or 0.0,
                          links.phy_bps[k]) for k in range(len(self.workers))
                  if links.rate_bps[k] and links.absent[k] != "out_of_range"]
        return backlog_drain_s(self.emulation.channel, self.options.probe_backlog_packets, probed)

    def send_all(self, ranks: list[int], iteration: int, payload: np.ndarray, links: IterationLinks) -> None:
        message = message_buffer((), WORK_HEADER + payload.size, self.pad)
        message[WORK_HEADER:WORK_HEADER + payload.size] = payload
        for rank in ranks:
            message = self.send(rank, KIND_WORK, iteration, payload, links, message=message)

    def deadline(self, t_start: float, timeouts: int = 1) -> float:
        """The monotonic time at which `timeouts` x --timeout-s (simulated seconds) have passed since t_start, not
        counting the time spent on sends that missed their deadline: that is not the other workers' lateness."""
        return t_start + self.clock.wall_s(timeouts * self.options.timeout_s) + self._stalled_s

    def iterate(self, iteration: int, present: list[int], links: IterationLinks, t_start: float) -> dict:
        """One iteration of Algorithm 1: the task's input to the present workers, their answers until the deadline,
        the task's plan for the blocks that did not arrive, and the task's combination; the record's task fields."""
        task, stretch = self.task, self.stretch
        stretch.begin()
        payload = task.next_input(iteration)
        master_s = stretch.hold() if stretch.active else 0.0
        queue_s = self.probes_queue_s(links)
        if queue_s:
            self.emulation.wait(queue_s)
        self.send_all(present, iteration, payload, links)
        self.write_pending()
        answers = self.collect(iteration, set(present), links, self.deadline(t_start))
        record = {} if queue_s is None else {"master_queue_s": queue_s}
        missing = [r for r in self.workers if r not in answers and self.bounds[r - 1][0] < self.bounds[r - 1][1]]
        plan = task.plan_missing(iteration, payload, missing, [r for r in self.workers if r in answers]) \
            if missing else []
        if plan:
            record["reassigned"] = self.send_again(iteration, plan, answers, links, self.deadline(t_start, 2))
        stretch.begin()
        record.update(task.combine(iteration, payload, answers))
        if stretch.active:
            record["master_compute_s"] = master_s + stretch.hold()
        return record

    def send_again(self, iteration: int, plan: list[Extra], answers: dict[int, Answer], links: IterationLinks,
                   deadline: float) -> list[dict]:
        """Send the planned blocks, then take each one's answer from its worker (which answers in order) into
        `answers`; what came back, as the record's `reassigned`."""
        by_worker: dict[int, list[Extra]] = {}
        for extra in plan:
            self.send(extra.by, KIND_EXTRA, iteration, extra.payload, links, extra_rows=extra.rows)
            by_worker.setdefault(extra.by, []).append(extra)
        done = []
        for rank, extras in by_worker.items():
            for extra in extras:
                buf = self.inbox.receive(deadline, source=rank)[1]
                if buf is not None and int(buf[RESULT_ITERATION]) == iteration:
                    answers[extra.rows_of] = answer_of(buf)
                    done.append({"rows_of": extra.rows_of, "by": rank})
        return done

    def collect(self, iteration: int, waiting: set[int], links: IterationLinks,
                deadline: float) -> dict[int, Answer]:
        """Each waited-for worker's answer to this iteration, in arrival order, until the deadline or until the task
        has enough (a coded task); the others are absent ("timeout"), unless the task had enough without them."""
        results, waited, heard = {}, set(waiting), set()
        while waiting and not self.task.enough(results):
            rank, buf = self.inbox.receive(deadline)
            if buf is None:
                break
            heard.add(rank)
            if rank in self.unresponsive:
                self._back(rank)  # any answer (a ping's, a late result) shows it is there again
            if int(buf[RESULT_ITERATION]) != iteration or rank not in waiting:
                self.stale_results += 1  # an answer that came after its iteration was closed
                continue
            k = rank - 1
            links.compute_s[k] = (links.compute_s[k] or 0.0) + float(buf[RESULT_COMPUTE_S])
            links.up_s[k] += float(buf[RESULT_UP_S])
            self.late_by_worker[rank] = int(buf[RESULT_LATE]), float(buf[RESULT_LATE_S])
            links.bytes_up[k] += buf.nbytes
            answer = answer_of(buf)
            if rank in results:  # a batched task's next batch (a worker's batches come in order)
                results[rank] = merge(results[rank], answer)
            elif int(buf[RESULT_BATCH]) == 0:
                results[rank] = answer
            if buf[RESULT_MORE] == 0:
                waiting.discard(rank)
        alive = set(results)
        if waiting and self.task.enough(results):
            # decoded without the rest: not absent, and not missed while their late answers keep coming (a dead
            # worker's never do: after UNRESPONSIVE_AFTER iterations unheard it is not sent to, only pinged)
            waiting, alive = set(), alive | heard
        for rank in waiting - set(results):  # a batched answer cut short by the deadline still counts
            links.absent[rank - 1] = "timeout"
        self._note_answers(iteration, waited, alive)
        return results

    def run(self) -> int:
        o, task = self.options, self.task
        self.bounds = self.planner.blocks(self.source.distances_m(0, 0.0) if self.source else {}, self.bounds)[1]
        self.comm.bcast(self.bounds, root=0)
        task.split(self.bounds)
        self.inbox = Inbox(self.comm, self.mpi, self.workers, TAG_RESULT, RESULT_HEADER + task.largest_result(),
                           self.pad)
        warmup_s = self.warm_up(task.input_floats())
        emulating = self.emulation is not None
        self.log.write(kinds.RUN_STARTED, warmup_s=warmup_s, task=task.name, workers=len(self.workers),
                       shards=self.bounds, emulate=o.emulate, pad_bits=o.pad_bits, speedup=self.clock.speedup,
                       channel=o.channel.name if emulating else None,
                       channel_validity=o.channel.validity() if emulating else None,
                       iterations=o.iterations, duration_s=o.duration_s, timeout_s=o.timeout_s,
                       on_missing=o.on_missing, allocation=o.allocation, pid=os.getpid(), device=o.device.name,
                       cpu_slowdown=o.device.slowdown, device_source=o.device.source,
                       worker_devices=[o.device_for(r).name for r in self.workers], replan_every=o.replan_every,
                       link_rates=o.link_rates)
        first = self.resume() if o.resume else 0
        self.wait_for_start()
        t_run, t_run_sim = time.monotonic(), self.clock.now_s()
        iteration, ended_by, idle_s = first, "iterations", 0.0
        while True:
            if o.iterations is not None and iteration >= o.iterations:
                break
            if o.duration_s is not None and self.clock.now_s() - t_run_sim >= o.duration_s:
                ended_by = "duration"
                break
            if self.end_at_s is not None and self.clock.now_s() >= self.end_at_s:
                ended_by = "end_at"
                break
            if self.stop_signal is not None:
                ended_by = "stopped"
                break
            t_start, start_unix, start_sim = time.monotonic(), time.time(), self.clock.now_s()
            distances = self.source.distances_m(iteration, start_sim - t_run_sim) if self.source else {}
            links = self.link(distances)
            if o.replan_every and task.replans:
                self.replan(iteration, distances, links)
            # a worker planned out (an empty block) is not sent work: it is not waited for either
            present = [r for r in self.workers if links.present(r) and self.bounds[r - 1][0] < self.bounds[r - 1][1]]
            self._stalled_s = 0.0
            if self._stuck or self.inbox.failed:
                self._reap()
            if self.unresponsive:
                self._ping_unresponsive()
            if present:
                idle_s = 0.0
            else:  # nobody reachable: wait, longer each time, instead of spinning through empty iterations
                idle_s = min(max(2 * idle_s, IDLE_FIRST_S), IDLE_MAX_S)
                self._hear_until(time.monotonic() + self.clock.wall_s(idle_s))
            record = self.iterate(iteration, present, links, t_start)
            self.pending = (iteration, start_unix, time.monotonic() - t_start, start_sim, self.clock.now_s(), links,
                            record)
            iteration += 1
            if o.checkpoint_s and time.monotonic() >= self._next_checkpoint_s:
                self.write_pending()  # a checkpoint holds no step whose record is not on disk before it
                self.checkpoint(iteration)
                self._next_checkpoint_s = time.monotonic() + o.checkpoint_s
        self.write_pending()
        self.checkpoint(iteration)
        stopped = self.stop_signal is not None
        if stopped:  # summary first: a worker's exit can end mpiexec, and hydra then kills this rank (issue 29)
            self.summarize(iteration, ended_by, t_run, t_run_sim)
        self.stop_workers(iteration)
        if not stopped:
            self.summarize(iteration, ended_by, t_run, t_run_sim)
        return 0

    def summarize(self, iteration: int, ended_by: str, t_run: float, t_run_sim: float) -> None:
        t = self.tally
        d = np.array(t.durations) if t.durations else np.array([np.nan])
        self.log.write(kinds.RUN_SUMMARY, task=self.task.name, iterations=iteration, complete_iterations=t.complete,
                       ended_by=ended_by, elapsed_s=time.monotonic() - t_run,
                       elapsed_sim_s=self.clock.now_s() - t_run_sim, mean_duration_s=float(np.mean(d)),
                       p95_duration_s=float(np.percentile(d, 95)),
                       absent_iterations={str(r): n for r, n in t.absences.items()},
                       stale_results=self.stale_results, lost_workers=sorted(self.unresponsive | self.agents_lost),
                       failed_workers=sorted(self.lost),
                       late_cpu_segments=self.stretch.late + sum(n for n, _ in self.late_by_worker.values()),
                       late_cpu_s_worst_rank=round(max([self.stretch.late_s, *(s for _, s in
                                                                               self.late_by_worker.values())]), 6),
                       **self.task.final())

    @property
    def finalizes(self) -> bool:
        """Whether MPI_Finalize can end the job: not with a rank that does not answer (it would wait for it), nor
        after SIGTERM (the launcher, which Finalize talks to, may be gone)."""
        return not (self.unresponsive or self.agents_lost or self.lost or self._stuck or self.undrained
                    or self.stop_signal)

    def request_stop(self, signum: int, _frame) -> None:
        """SIGTERM (a supervisor restarting the job, or the launcher gone): the loop ends after this iteration and
        the run ends as at its end, checkpoint and summary written (`ended_by` "stopped")."""
        self.stop_signal = signal.Signals(signum).name

    def stop_workers(self, iteration: int) -> None:
        """STOP to every worker, saying whether MPI_Finalize will run; each send gives up at its deadline."""
        self._reap()
        finalizes = self.finalizes
        stop = message_buffer(work_header(KIND_STOP, iteration, extra_rows=0 if finalizes else 1), 0, self.pad)
        timeout_s = self.clock.wall_s(self.options.timeout_s)
        restarted = self.source.restarted if self.source is not None else set()
        for rank in self.workers:
            if rank in self.lost or rank in restarted:  # a send to a rebooted companion's old connection: a reset
                continue
            if rank in self.unresponsive or rank in self.agents_lost:  # it may never take it: do not wait for that
                request = self._isend(rank, stop)
                if request is not None:
                    self._pings[rank] = (request, stop)
            elif not self._send_within(rank, stop, timeout_s):
                stop = stop.copy()
        if finalizes:
            self._drain(time.monotonic() + timeout_s)
        self.inbox.close(wait=self.finalizes)

    def _drain(self, deadline: float) -> None:
        """Each worker's answers up to its STOPPED_ANSWER, the last it sends: MPI_Finalize fails (and the workers,
        waiting for the master in theirs, hang) while a message sent to the master is unmatched: a batched task's
        batches after the last decode, or any late answer (measured: 2 such in about 1 of 25 BPCC runs under
        load). A worker whose STOPPED_ANSWER does not come by the deadline leaves the master unable to finalize."""
        for rank in self.workers:
            if rank in self.lost or rank in self.unresponsive or rank in self.agents_lost:
                continue
            while True:
                buf = self.inbox.receive(deadline, source=rank)[1]
                if buf is None:
                    self.undrained.add(rank)
                    break
                if int(buf[RESULT_ITERATION]) == STOPPED_ANSWER[RESULT_ITERATION]:
                    break
                self.stale_results += 1

    def resume(self) -> int:
        """--resume: the task's state and the iteration count from the checkpoint in --out (checked on every rank
        before MPI started); the next iteration to run."""
        iteration, arrays = load_checkpoint(self.options.out, self.task.name)
        self.task.resume(arrays)
        self.checkpoint_iteration = iteration
        self.log.write(kinds.RESUMED, iteration=iteration, checkpoint=str(checkpoint_path(self.options.out)))
        return iteration

    def wait_for_start(self) -> None:
        """--start-file: the job is set up (ranks, connections, data) before the go, so its start-up time does not
        land in the experiment: at a speed-up it would be simulated seconds of flight without computing."""
        path = self.options.start_file
        if not path:
            return
        deadline = time.monotonic() + self.options.idle_timeout_s
        while not os.path.exists(path):
            if self.stop_signal is not None:
                return
            if time.monotonic() > deadline:
                raise TimeoutError(f"--start-file {path} did not appear within {self.options.idle_timeout_s:g} s")
            time.sleep(0.005)
        self.end_at_s = read_start_file(path) or self.options.end_at_s
        self.log.write(kinds.STARTED, start_file=path, end_at_s=self.end_at_s)

    def checkpoint(self, iteration: int) -> None:
        """results.npz as of this iteration, replaced atomically: a crash of the master leaves the last whole one.
        A full disk (ENOSPC, EDQUOT, EFBIG) costs this checkpoint only: the partial file is removed, the previous
        whole one kept, a checkpoint_failed record says so, training goes on and the next checkpoint tries again."""
        results = self.task.results()
        if not results and not self.options.save_results:
            return
        path = os.path.join(self.options.out, kinds.RESULTS.name)
        partial = path + ".partial.npz"
        try:
            np.savez(partial, iteration=np.array(iteration), task=np.array(self.task.name), **results)
            os.replace(partial, path)
        except OSError as err:
            if err.errno not in DISK_FULL:
                raise
            with contextlib.suppress(OSError):
                os.remove(partial)
            self.log.write(kinds.CHECKPOINT_FAILED, iteration=iteration,
                           error=f"{errno.errorcode.get(err.errno, err.errno)}: {err.strerror}",
                           kept_iteration=self.checkpoint_iteration)
            return
        self.checkpoint_iteration = iteration

    def write_pending(self) -> None:
        """The previous iteration's bookkeeping and record, done once this iteration's inputs are out: it overlaps
        the workers' computing instead of delaying the next inputs. A crash loses only the iteration in flight."""
        if self.pending is None:
            return
        iteration, start_unix, duration_s, start_sim, end_sim, links, record = self.pending
        self.pending = None
        t = self.tally
        t.durations.append(duration_s)
        t.complete += record["complete"]
        for rank, why in zip(self.workers, links.absent, strict=True):
            if why is not None:
                t.absences[rank] += 1
        end_s = start_unix + duration_s
        self.log.write(kinds.ITERATION, t_s=end_s, iteration=iteration, start_s=start_unix, end_s=end_s,
                       duration_s=duration_s, start_sim_s=start_sim, duration_sim_s=end_sim - start_sim,
                       workers=links.record(self.workers, self.vehicles), **record)

    def warm_up(self, floats: int) -> float:
        """One untimed exchange of an input-sized message with every worker: MPI sets up its connections and
        buffers on first use, which would otherwise land in the first iteration's time."""
        t0 = time.monotonic()
        message = message_buffer(work_header(KIND_WARMUP), floats, self.pad)
        message[WORK_HEADER:] = 0.0
        deadline = t0 + self.options.timeout_s  # wall seconds: connections cost the machine's time, not the link's
        workers = [rank for rank in self.workers if rank not in self.lost]  # refused ones have ended
        for rank in workers:
            if not self._send_within(rank, message, deadline - time.monotonic()):
                raise TimeoutError(f"worker {rank} did not take the warm-up within {self.options.timeout_s:g} s")
        for rank in workers:
            if self.inbox.receive(deadline, source=rank)[0] is None:
                raise TimeoutError(f"worker {rank} did not answer the warm-up within {self.options.timeout_s:g} s")
        return time.monotonic() - t0


def answer_of(buf: np.ndarray) -> Answer:
    """A worker's answer as its task's `work` returned it (the result message without its header)."""
    return Answer(buf[RESULT_HEADER:], int(buf[RESULT_ROWS]), float(buf[RESULT_SSE]))


def merge(first: Answer, then: Answer) -> Answer:
    """A worker's batches so far as one answer: results in batch order, rows and squared errors added."""
    return Answer(np.concatenate([first.values, then.values]), first.rows + then.rows, first.sse + then.sse)


def read_start_file(path: str) -> float | None:
    """end_at_s from a start file, if it gives one (an empty file is a plain go)."""
    try:
        with open(path) as f:
            text = f.read().strip()
        value = json.loads(text).get("end_at_s") if text else None
    except (OSError, ValueError, AttributeError) as err:
        raise NacError(f"--start-file {path}: expected nothing or a JSON object with end_at_s ({err})") from None
    if value is not None and not (isinstance(value, (int, float)) and math.isfinite(value)):
        raise NacError(f"--start-file {path}: end_at_s must be a number, got {value!r}")
    return value


def problem_of(options: ComputeOptions) -> str:
    """What a rank would compute, in one line: the task, its sizes, seed, code and step, and its input files. Every
    worker's must be the master's."""
    o = options
    return (f"task {o.task} (m {o.m}, n {o.n}, l {o.l}, seed {o.seed}, code k {o.code_k} s {o.code_s} r "
            f"{o.code_redundancy:g}, learning rate {o.learning_rate:g}; {o.task_class.inputs_of(o)})")


def joined(comm, mpi, wait_s: float) -> bool:
    """Whether every rank came to the start within wait_s (wall): the start's collectives (gather, bcast), which
    have no deadline, then complete at once. Without this, a rank that hung before them (a companion stopped while
    starting) held every other rank, and the job, for ever."""
    try:
        return bool(wait_for(comm.Ibarrier().Test, time.monotonic() + wait_s))
    except mpi.Exception:  # a rank that died before the start
        return False


def end_without_finalize(code: int) -> None:
    """MPI_Finalize waits for every rank, a lost one too: with everything on disk, the rank ends here."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def main(argv: list[str] | None = None) -> int:
    options = parse_args(argv)  # bad input: exit 2 on every rank, before MPI starts any work
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    comm.Set_errhandler(MPI.ERRORS_RETURN)  # a dead peer is an exception to handle, not the end of this rank
    # hydra's notice that a rank died: the job finds lost ranks by their silence and needs no handler for it
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    # ranks run in sessions of their own (hydra's doing): if their proxy is killed, they go too; the master by
    # SIGTERM, which stops it at the end of its iteration with its checkpoint and summary written (when mpiexec
    # dies, the proxies kill their ranks themselves: the master then leaves its last checkpoint)
    die_with_parent(signal.SIGTERM if comm.Get_rank() == 0 else signal.SIGKILL)
    if comm.Get_size() < 2:
        sys.stderr.write("nac-onboard compute: needs at least 2 ranks (mpiexec -n N+1 ...): a master and a worker\n")
        return 2
    try:  # every rank computes the same verdict, so every rank exits 2 and none waits for another
        options.task_class.check_workers(options, comm.Get_size() - 1)
        if options.energy_wh and len(options.energy_wh) != comm.Get_size() - 1:
            raise ValueError(f"--energy-wh gives {len(options.energy_wh)} values: one per worker expected")
    except ValueError as err:
        sys.stderr.write(f"nac-onboard compute: --task {options.task} with {comm.Get_size() - 1} workers: {err}\n")
        # not `return 2`: python -m mpi4py turns a failing exit into MPI_Abort, and hydra, with every rank
        # aborting at once, now and then dies of SIGPIPE instead of passing the 2 on (1 of 7 runs, measured)
        end_without_finalize(2)
    if not joined(comm, MPI, options.clock.wall_s(options.idle_timeout_s)):
        sys.stderr.write(f"nac-onboard compute rank {comm.Get_rank()} ({options.vehicle_of(comm.Get_rank())}): not "
                         f"every rank started within --idle-timeout-s {options.idle_timeout_s:g} s; ending (exit 3)\n")
        end_without_finalize(3)
    problem = problem_of(options)
    problems = comm.gather(problem, root=0)  # a companion back with another data set or NAC
    agreed = comm.bcast([p == problems[0] for p in problems] if comm.Get_rank() == 0 else None, root=0)
    if not agreed[comm.Get_rank()]:
        sys.stderr.write(f"nac-onboard compute rank {comm.Get_rank()} ({options.vehicle_of(comm.Get_rank())}): "
                         f"refused: this rank would compute {problem}, the master another problem\n")
        end_without_finalize(2)
    try:
        os.makedirs(options.out, exist_ok=True)
        if comm.Get_rank() == 0:
            with JsonlLog(os.path.join(options.out, kinds.COMPUTE_LOG.name)) as log:
                master = Master(comm, MPI, options, log)
                for rank, problem in enumerate(problems):
                    if problem != problems[0]:
                        master.refuse(rank, f"it would compute {problem}; the master {problems[0]}")
                signal.signal(signal.SIGTERM, master.request_stop)
                code = master.run()
            if not master.finalizes:
                end_without_finalize(code)
            return code
        with JsonlLog(os.path.join(options.out, kinds.RANK_LOG.file_name(rank=options.log_number(comm.Get_rank())))) \
                as log:
            log.write(kinds.WORKER_STARTED, rank=comm.Get_rank(), pid=os.getpid(), host=MPI.Get_processor_name())
            finalizes = run_worker(comm, MPI, options, log)
            log.write(kinds.WORKER_STOPPED, rank=comm.Get_rank(), finalizes=finalizes)
        if not finalizes:
            end_without_finalize(0)
        return 0
    except Exception as err:  # one failing rank must end the job, not leave the others waiting
        code = err.exit_code if isinstance(err, NacError) else 1
        sys.stderr.write(f"nac-onboard compute rank {comm.Get_rank()}: {type(err).__name__}: {err}\n")
        sys.stderr.flush()
        comm.Abort(code)
        return code

