"""Waiting on MPI with deadlines, for the master and the workers alike (runner.py).

A rank never waits on a peer in a blocking MPI call (the start's collectives come after a barrier with a deadline,
runner.joined): such a call waits for a peer that may be dead, stopped or out of range for good. And
a rank that waits for anything keeps taking the messages already in. A message larger than MPI's eager limit (a
matmul input of 10,000 rows, or any message with a channel's overhead as real bytes, --pad-bits) goes by rendezvous:
its send waits, blocked, until the receiver posts a receive for it. With one posted receive per peer, a receive that
has completed and is left untaken (a coded task's late answer, after the master decoded without it) stalls the
peer's next large send; measured: a gradient-coded job with 12.5 kB messages had its slowest worker blocked in a
send the master never took, and `mpiexec` never ended."""

from __future__ import annotations

import os
import time

import numpy as np


class Poller:
    """Waits on MPI with a deadline: spins (yielding the core) for the first 2 ms, then naps, so that ranks
    sharing a core neither starve each other nor add latency to fast exchanges."""

    def __init__(self):
        self.started = time.monotonic()

    def pause(self) -> None:
        if time.monotonic() - self.started < 0.002:
            os.sched_yield()
        else:
            time.sleep(0.0005)


def wait_for(done, deadline: float, meanwhile=None) -> bool | None:
    """Poll done() until it holds: True; None at the deadline (time.monotonic); False as soon as meanwhile(), called
    between polls, gives a reason to stop waiting."""
    poller = None
    while not done():
        if meanwhile is not None and meanwhile():
            return False
        if poller is None:
            poller = Poller()
        elif time.monotonic() >= deadline:
            return None
        poller.pause()
    return True


class Inbox:
    """One posted receive per peer, re-posted as each message is taken. Waiting polls the posted receives with a
    deadline: on ranks that share a core, MPICH's own Probe and Iprobe loops starve the other rank (measured: 125
    iterations/s instead of thousands), while testing posted receives does not. Messages taken while the rank waited
    on something else (take_ready) are kept, in order, for receive()."""

    def __init__(self, comm, mpi, sources: list[int], tag: int, floats: int, pad: int = 0):
        self.comm, self.mpi, self.tag, self.pad = comm, mpi, tag, pad
        self.sources = list(sources)
        self.buffers = [np.empty(floats + pad) for _ in self.sources]
        self.requests = [self._post(k) for k in range(len(self.sources))]
        self.status = mpi.Status()
        self.failed: dict[int, str] = {}  # source -> the MPI error its receive ended with
        self.taken: list[tuple[int, np.ndarray]] = []  # (source, message) taken by take_ready, not yet received

    def _drop_failed(self) -> None:
        """After MPI reported an error on a posted receive (errors are returned, not fatal): find the peers whose
        receives failed and stop receiving from them."""
        for k, request in enumerate(self.requests):
            try:
                request.Test()
            except self.mpi.Exception as err:
                self.failed[self.sources[k]] = str(err)
                self.requests[k] = self.mpi.REQUEST_NULL

    def _post(self, k: int):
        return self.comm.Irecv([self.buffers[k], self.mpi.DOUBLE], source=self.sources[k], tag=self.tag)

    def _take_one(self, source: int | None = None) -> tuple[int, np.ndarray] | None:
        """(source, message) of a completed receive (from `source` only, if given), its receive re-posted; None if
        no receive has completed."""
        mpi, status = self.mpi, self.status
        while True:
            k = None if source is None else self.sources.index(source)
            try:
                index, done = mpi.Request.Testany(self.requests if k is None else [self.requests[k]], status)
            except mpi.Exception:
                self._drop_failed()
                continue
            if not done or index == mpi.UNDEFINED:
                return None
            k = index if k is None else k
            message = self.buffers[k][:status.Get_count(mpi.DOUBLE) - self.pad].copy()
            self.requests[k] = self._post(k)
            return self.sources[k], message

    def take_ready(self) -> None:
        """Take every message already in, re-posting its receive, for receive() to return later: a peer's large
        send then finds a receive posted while this rank waits on something else."""
        while (item := self._take_one()) is not None:
            self.taken.append(item)

    def receive(self, deadline: float, source: int | None = None):
        """(source, message) of the next message (from `source` only, if given), or (None, None) at the deadline."""
        for i, item in enumerate(self.taken):
            if source is None or item[0] == source:
                return self.taken.pop(i)
        poller = None  # made on the first miss: a message already there costs no clock reads
        while True:
            item = self._take_one(source)
            if item is not None:
                return item
            if poller is None:
                poller = Poller()
            elif time.monotonic() >= deadline:
                return None, None
            poller.pause()

    def close(self, wait: bool = True) -> None:
        """Cancel the posted receives; wait for the cancellations unless told not to (a rank that does not answer
        can make that wait forever)."""
        for request in self.requests:
            if request != self.mpi.REQUEST_NULL:
                request.Cancel()
        if wait:
            self.mpi.Request.Waitall(self.requests)
