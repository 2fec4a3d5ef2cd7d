"""Networked airborne computing over MPI (DESIGN.md 5, Algorithm 1): rank 0 is the master, ranks 1..N workers.

    mpiexec -n N+1 -bind-to core python -m mpi4py -m nac_onboard.compute --task matmul|linreg [options]

Each iteration the master sends every worker in range its input (B for matmul, the weights for linreg), waits
for the results until --timeout-s, and combines what arrived. With --emulate sleep (the research's method) the
master sleeps I/C before each send and tells the worker the link's capacity C, so the worker sleeps before its
answer too; C comes from the channel model at the two vehicles' distance, and below the model's minimum rate
the worker is out of range: nothing is sent. A worker that misses an iteration is absent for it (linreg carries
on with the gradients that arrived, weighted by shard size; matmul re-assigns the missing rows to live workers or
marks the iteration incomplete, --on-missing) and takes part again as soon as it answers. A rank that dies or
raises aborts the whole job (exit code != 0): the master's records, one line each, are all on disk by then.

Records (JSON Lines, --out DIR/compute.jsonl): run_started, one `iteration` record per iteration, run_summary.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field

import numpy as np

from nac_onboard.compute import kernels
from nac_onboard.compute.options import ComputeOptions, build_source, parse_args
from nac_onboard.flight_log import JsonlLog

TAG_WORK, TAG_RESULT = 1, 2
KIND_WORK, KIND_EXTRA, KIND_STOP, KIND_WARMUP = 1.0, 2.0, 3.0, 4.0
HEADER = 4  # master -> worker: kind, iteration, rate_bps, rows of A that follow (extra work)
RESULT_HEADER = 5  # worker -> master: iteration, compute_s, up_s, rows, sse
BITS_PER_FLOAT = 64


def matmul_inputs(seed: int, m: int, n: int, a_path: str | None = None):
    """A (m x n) from the seed or a .npy file, and the generator of the B (n x l) sent each iteration."""
    rng = np.random.default_rng(seed)
    a = np.load(a_path) if a_path else rng.standard_normal((m, n))
    return a, np.random.default_rng(seed + 1)


class _Poller:
    """Waits on MPI with a deadline: spins (yielding the core) for the first 2 ms, then naps, so that ranks
    sharing a core neither starve each other nor add latency to fast exchanges."""

    def __init__(self):
        self.started = time.monotonic()

    def pause(self) -> None:
        if time.monotonic() - self.started < 0.002:
            os.sched_yield()
        else:
            time.sleep(0.0005)


class Inbox:
    """One posted receive per peer, re-posted as each message is taken. Waiting polls the posted receives with a
    deadline: on ranks that share a core, MPICH's own Probe and Iprobe loops starve the other rank (measured: 125
    iterations/s instead of thousands), while testing posted receives does not."""

    def __init__(self, comm, mpi, sources: list[int], tag: int, floats: int):
        self.comm, self.mpi, self.tag = comm, mpi, tag
        self.sources = list(sources)
        self.buffers = [np.empty(floats) for _ in self.sources]
        self.requests = [self._post(k) for k in range(len(self.sources))]
        self.status = mpi.Status()

    def _post(self, k: int):
        return self.comm.Irecv([self.buffers[k], self.mpi.DOUBLE], source=self.sources[k], tag=self.tag)

    def receive(self, deadline: float, source: int | None = None):
        """(source, message) of the next message (from `source` only, if given), or (None, None) at the deadline."""
        requests = self.requests if source is None else [self.requests[self.sources.index(source)]]
        testany, undefined, status = self.mpi.Request.Testany, self.mpi.UNDEFINED, self.status
        poller = None  # made on the first miss: a message already there costs no clock reads
        while True:
            index, done = testany(requests, status)
            if done and index != undefined:
                k = index if source is None else self.sources.index(source)
                message = self.buffers[k][:status.Get_count(self.mpi.DOUBLE)].copy()
                self.requests[k] = self._post(k)
                return self.sources[k], message
            if poller is None:
                poller = _Poller()
            elif time.monotonic() >= deadline:
                return None, None
            poller.pause()

    def close(self) -> None:
        for request in self.requests:
            request.Cancel()
        self.mpi.Request.Waitall(self.requests)


def largest_input(options: ComputeOptions, bounds: list[tuple[int, int]]) -> int:
    """Floats in the largest message a worker can get: its input, or a re-assigned block of A with B."""
    if options.task == "linreg":
        from nac_onboard.compute.forestfires import FEATURES

        return HEADER + len(FEATURES)
    rows = max(stop - start for start, stop in bounds)
    return HEADER + rows * options.n + options.n * options.l


def largest_result(options: ComputeOptions, bounds: list[tuple[int, int]]) -> int:
    if options.task == "linreg":
        from nac_onboard.compute.forestfires import FEATURES

        return RESULT_HEADER + len(FEATURES)
    return RESULT_HEADER + max(stop - start for start, stop in bounds) * options.l


# ---- workers ---------------------------------------------------------------------------------------------------
def run_worker(comm, mpi, options: ComputeOptions) -> None:
    rank = comm.Get_rank()
    bounds = comm.bcast(None, root=0)
    start, stop = bounds[rank - 1]
    if options.task == "matmul":
        a, _ = matmul_inputs(options.seed, options.m, options.n, options.a_path)
        block = a[start:stop]
    else:
        from nac_onboard.compute import forestfires

        x, y = forestfires.load(forestfires.find_csv(options.data))
        x_shard, y_shard = x[start:stop], y[start:stop]
    inbox = Inbox(comm, mpi, [0], TAG_WORK, largest_input(options, bounds))
    channel = options.channel_model()
    answers = {}  # reused answer buffers by result size: no allocation per iteration
    while True:
        _, message = inbox.receive(time.monotonic() + options.idle_timeout_s)
        if message is None:
            sys.stderr.write(f"worker {rank}: nothing from the master for {options.idle_timeout_s:g} s; aborting\n")
            comm.Abort(3)
        kind, iteration, rate_bps, extra_rows = message[:HEADER].tolist()  # Python floats: cheaper to test
        if kind == KIND_STOP:
            inbox.close()
            return
        if kind == KIND_WARMUP:
            comm.Send([np.array([-1.0, 0.0, 0.0, 0.0, 0.0]), mpi.DOUBLE], dest=0, tag=TAG_RESULT)
            continue
        payload = message[HEADER:]
        t0 = time.perf_counter()
        if options.task == "matmul":
            rows = int(extra_rows)
            if kind == KIND_EXTRA:
                a_rows, b = payload[:rows * options.n].reshape(rows, options.n), payload[rows * options.n:]
                result = kernels.matmul_block(a_rows, b.reshape(options.n, options.l)).ravel()
            else:
                result = kernels.matmul_block(block, payload.reshape(options.n, options.l)).ravel()
                rows = len(block)
            sse = 0.0
        else:
            gradient, sse, rows = kernels.local_gradient(x_shard, y_shard, payload)
            result = gradient
        compute_s = time.perf_counter() - t0
        up_s = channel.transfer_s(result.size * BITS_PER_FLOAT, rate_bps)
        if up_s:
            time.sleep(up_s)
        answer = answers.get(result.size)
        if answer is None:
            answer = answers[result.size] = np.empty(RESULT_HEADER + result.size)
        answer[:RESULT_HEADER] = (iteration, compute_s, up_s, rows, sse)
        answer[RESULT_HEADER:] = result
        comm.Send([answer, mpi.DOUBLE], dest=0, tag=TAG_RESULT)


# ---- master ----------------------------------------------------------------------------------------------------
class IterationLinks:
    """What happened on each worker's link in one iteration, one list per field (index = rank - 1): the record
    keeps this columnar shape, which is also the cheapest to encode at thousands of iterations a second."""

    FIELDS = ("distance_m", "rate_bps", "absent", "bytes_down", "bytes_up", "down_s", "up_s", "compute_s")

    def __init__(self, workers: int):
        self.distance_m: list = [None] * workers
        self.rate_bps: list = [None] * workers
        self.absent: list = [None] * workers  # None = present; else why: out_of_range, no_position, timeout
        self.bytes_down = [0] * workers
        self.bytes_up = [0] * workers
        self.down_s = [0.0] * workers
        self.up_s = [0.0] * workers
        self.compute_s: list = [None] * workers

    def present(self, rank: int) -> bool:
        return self.absent[rank - 1] is None

    def record(self, ranks: list[int], vehicles: list[str]) -> dict:
        out = {"rank": ranks, "vehicle": vehicles, "present": [a is None for a in self.absent]}
        out.update((name, getattr(self, name)) for name in self.FIELDS)
        return out


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
        self.channel = options.channel_model()
        self.stale_results = 0
        self.inbox: Inbox | None = None  # posted once the shards are known
        self.pending: tuple | None = None  # the last iteration, not yet tallied and written
        self.tally = Tally({r: 0 for r in self.workers})
        self.saved: dict[str, np.ndarray] = {}  # --save-results

    def link(self, distances: dict) -> IterationLinks:
        """Per worker: distance, emulated rate and whether it is in range this iteration."""
        links = IterationLinks(len(self.workers))
        for k, rank in enumerate(self.workers):
            d = distances.get(rank) if distances else None
            links.distance_m[k] = d
            if self.options.emulate == "sleep":
                if d is None:
                    links.absent[k] = "no_position"
                else:
                    links.rate_bps[k] = rate = self.channel.capacity_bps(d)
                    if rate < self.channel.min_rate_bps:
                        links.absent[k] = "out_of_range"
        return links

    def allocation(self, rows: int) -> list[tuple[int, int]]:
        shares = [1.0] * len(self.workers)
        if self.options.allocation == "capacity":
            links = self.link(self.source.distances_m(0, 0.0) if self.source else {})
            shares = [rate or 0.0 for rate in links.rate_bps]
            if sum(shares) <= 0:
                shares = [1.0] * len(self.workers)
        return kernels.split_rows(rows, shares)

    def send(self, rank: int, kind: float, iteration: int, payload: np.ndarray, links: IterationLinks,
             extra_rows: int = 0, message: np.ndarray | None = None) -> None:
        """Send one input; `message` is a reusable buffer whose payload part is already filled."""
        k = rank - 1
        rate = links.rate_bps[k] or 0.0
        down_s = self.channel.transfer_s(payload.size * BITS_PER_FLOAT, rate)
        if down_s:
            time.sleep(down_s)  # the research's emulation: the transfer takes I/C before it happens
        if message is None:
            message = np.empty(HEADER + payload.size)
            message[HEADER:] = payload
        message[:HEADER] = (kind, iteration, rate, extra_rows)
        self.comm.Send([message, self.mpi.DOUBLE], dest=rank, tag=TAG_WORK)
        links.bytes_down[k] += message.nbytes
        links.down_s[k] += down_s

    def send_all(self, ranks: list[int], iteration: int, payload: np.ndarray, links: IterationLinks) -> None:
        message = np.empty(HEADER + payload.size)
        message[HEADER:] = payload
        for rank in ranks:
            self.send(rank, KIND_WORK, iteration, payload, links, message=message)

    def collect(self, iteration: int, waiting: set[int], links: IterationLinks,
                deadline: float) -> dict[int, np.ndarray]:
        results = {}
        while waiting:
            rank, buf = self.inbox.receive(deadline)
            if buf is None:
                break
            if int(buf[0]) != iteration or rank not in waiting:
                self.stale_results += 1  # an answer that came after its iteration was closed
                continue
            waiting.discard(rank)
            k = rank - 1
            links.compute_s[k], links.up_s[k] = float(buf[1]), float(buf[2])
            links.bytes_up[k] += buf.nbytes
            results[rank] = buf
        for rank in waiting:
            links.absent[rank - 1] = "timeout"
        return results

    def run(self) -> int:
        o = self.options
        if o.task == "matmul":
            a, b_rng = matmul_inputs(o.seed, o.m, o.n, o.a_path)
            bounds = self.allocation(len(a))
            matmul_state = {"a": a, "b_rng": b_rng, "bounds": bounds}
            input_floats = o.n * o.l
        else:
            from nac_onboard.compute import forestfires

            x, y = forestfires.load(forestfires.find_csv(o.data))
            bounds = self.allocation(len(y))
            linreg_state = {"w": np.zeros(x.shape[1]), "rows": len(y), "cost": None}
            input_floats = x.shape[1]
        self.comm.bcast(bounds, root=0)
        self.inbox = Inbox(self.comm, self.mpi, self.workers, TAG_RESULT, largest_result(o, bounds))
        warmup_s = self.warm_up(input_floats)
        self.log.write("run_started", warmup_s=warmup_s, task=o.task, workers=len(self.workers), shards=bounds,
                       emulate=o.emulate, channel=self.channel.name if o.emulate == "sleep" else None,
                       channel_validity=self.channel.validity() if o.emulate == "sleep" else None,
                       iterations=o.iterations, duration_s=o.duration_s, timeout_s=o.timeout_s,
                       on_missing=o.on_missing, allocation=o.allocation, pid=os.getpid())
        t_run = time.monotonic()
        iteration, ended_by = 0, "iterations"
        while True:
            if o.iterations is not None and iteration >= o.iterations:
                break
            if o.duration_s is not None and time.monotonic() - t_run >= o.duration_s:
                ended_by = "duration"
                break
            t_start, start_unix = time.monotonic(), time.time()
            links = self.link(self.source.distances_m(iteration, t_start - t_run) if self.source else {})
            present = [r for r in self.workers if links.present(r)]
            if o.task == "matmul":
                record = self.matmul_iteration(iteration, present, links, t_start, matmul_state)
            else:
                record = self.linreg_iteration(iteration, present, links, t_start, linreg_state)
            self.pending = (iteration, start_unix, time.monotonic() - t_start, links, record)
            iteration += 1
        self.write_pending()
        for rank in self.workers:
            self.comm.Send([np.array([KIND_STOP, iteration, 0.0, 0.0]), self.mpi.DOUBLE], dest=rank, tag=TAG_WORK)
        self.inbox.close()
        if o.task == "linreg":
            self.saved["weights"] = linreg_state["w"]
        if o.save_results or o.task == "linreg":
            np.savez(os.path.join(o.out, "results.npz"), **self.saved)
        t = self.tally
        d = np.array(t.durations) if t.durations else np.array([np.nan])
        self.log.write("run_summary", task=o.task, iterations=iteration, complete_iterations=t.complete,
                       ended_by=ended_by, elapsed_s=time.monotonic() - t_run, mean_duration_s=float(np.mean(d)),
                       p95_duration_s=float(np.percentile(d, 95)), absent_iterations={str(r): n for r, n in
                                                                                     t.absences.items()},
                       final_cost=linreg_state["cost"] if o.task == "linreg" else None,
                       stale_results=self.stale_results)
        return 0

    def write_pending(self) -> None:
        """The previous iteration's bookkeeping and record, done once this iteration's inputs are out: it overlaps
        the workers' computing instead of delaying the next inputs. A crash loses only the iteration in flight."""
        if self.pending is None:
            return
        iteration, start_unix, duration_s, links, record = self.pending
        self.pending = None
        t = self.tally
        t.durations.append(duration_s)
        t.complete += record["complete"]
        for rank, why in zip(self.workers, links.absent, strict=True):
            if why is not None:
                t.absences[rank] += 1
        end_s = start_unix + duration_s
        self.log.write("iteration", t_s=end_s, iteration=iteration, start_s=start_unix, end_s=end_s,
                       duration_s=duration_s, workers=links.record(self.workers, self.vehicles), **record)

    def matmul_iteration(self, iteration: int, present: list[int], links: IterationLinks, t_start: float,
                         state: dict) -> dict:
        o = self.options
        b = state["b_rng"].standard_normal((o.n, o.l))
        self.send_all(present, iteration, b.ravel(), links)
        self.write_pending()
        results = self.collect(iteration, set(present), links, t_start + o.timeout_s)
        blocks = {r: results[r][RESULT_HEADER:].reshape(-1, o.l) for r in results}
        record = {}
        missing = [r for r in self.workers if r not in blocks]
        if missing and o.on_missing == "reassign" and blocks:
            record["reassigned"] = self.reassign(iteration, state["a"], b, state["bounds"], missing, blocks, links,
                                                 t_start + 2 * o.timeout_s)
        record["complete"] = all(r in blocks for r in self.workers)
        if record["complete"] and o.save_results:
            self.saved[f"B_{iteration}"] = b
            self.saved[f"C_{iteration}"] = kernels.stack_blocks([blocks[r] for r in self.workers])
        return record

    def linreg_iteration(self, iteration: int, present: list[int], links: IterationLinks, t_start: float,
                         state: dict) -> dict:
        o = self.options
        self.send_all(present, iteration, state["w"], links)
        self.write_pending()
        results = self.collect(iteration, set(present), links, t_start + o.timeout_s)
        if not results:
            return {"cost": None, "rows_used": 0, "complete": False}
        parts = [(buf[RESULT_HEADER:], float(buf[4]), int(buf[3])) for buf in results.values()]
        gradient, cost, rows = kernels.combine_gradients(parts)
        state["w"] = state["w"] - o.learning_rate * gradient
        state["cost"] = cost
        return {"cost": cost, "rows_used": rows, "complete": rows == state["rows"]}

    def warm_up(self, floats: int) -> float:
        """One untimed exchange of an input-sized message with every worker: MPI sets up its connections and
        buffers on first use, which would otherwise land in the first iteration's time."""
        t0 = time.monotonic()
        message = np.zeros(HEADER + floats)
        message[0] = KIND_WARMUP
        for rank in self.workers:
            self.comm.Send([message, self.mpi.DOUBLE], dest=rank, tag=TAG_WORK)
        for rank in self.workers:
            if self.inbox.receive(t0 + self.options.timeout_s, source=rank)[0] is None:
                raise TimeoutError(f"worker {rank} did not answer the warm-up within {self.options.timeout_s:g} s")
        return time.monotonic() - t0

    def reassign(self, iteration, a, b, bounds, missing, blocks, links, deadline) -> list[dict]:
        """Send each missing block's rows of A, with B, to a worker that answered; wait for those answers."""
        helpers = [r for r in self.workers if r in blocks]
        plan = {}
        for k, rank in enumerate(missing):
            helper = helpers[k % len(helpers)]
            start, stop = bounds[rank - 1]
            payload = np.concatenate([a[start:stop].ravel(), b.ravel()])
            self.send(helper, KIND_EXTRA, iteration, payload, links, extra_rows=stop - start)
            plan.setdefault(helper, []).append(rank)
        done = []
        for helper, ranks in plan.items():
            for rank in ranks:
                _, buf = self.inbox.receive(deadline, source=helper)
                if buf is not None and int(buf[0]) == iteration:
                    blocks[rank] = buf[RESULT_HEADER:].reshape(-1, self.options.l)
                    done.append({"rows_of": rank, "by": helper})
        return done


def main(argv: list[str] | None = None) -> int:
    options = parse_args(argv)  # bad input: exit 2 on every rank, before MPI starts any work
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    if comm.Get_size() < 2:
        sys.stderr.write("nac-onboard compute: needs at least 2 ranks (mpiexec -n N+1 ...): a master and a worker\n")
        return 2
    try:
        os.makedirs(options.out, exist_ok=True)
        if comm.Get_rank() == 0:
            with JsonlLog(os.path.join(options.out, "compute.jsonl")) as log:
                return Master(comm, MPI, options, log).run()
        with JsonlLog(os.path.join(options.out, f"rank-{comm.Get_rank()}.jsonl")) as log:
            log.write("worker_started", rank=comm.Get_rank(), pid=os.getpid(), host=MPI.Get_processor_name())
            run_worker(comm, MPI, options)
            log.write("worker_stopped", rank=comm.Get_rank())
        return 0
    except Exception as err:  # one failing rank must end the job, not leave the others waiting
        sys.stderr.write(f"nac-onboard compute rank {comm.Get_rank()}: {type(err).__name__}: {err}\n")
        sys.stderr.flush()
        comm.Abort(1)
        return 1

