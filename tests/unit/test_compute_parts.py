"""The computing model's pure parts: channel models against hand-computed values, kernels, the data set."""

import dataclasses
import hashlib
import io
import math
import os
import sys
import threading
import zipfile

import numpy as np
import pytest

from nac_onboard.compute import forestfires, kernels
from nac_onboard.compute.allocation import Planner
from nac_onboard.compute.launch import core_binding, cpu_per_host, mpiexec_command
from nac_onboard.compute.messages import KIND_WORK
from nac_onboard.compute.options import ComputeOptions
from nac_onboard.compute.positions import ScriptedDistances
from nac_onboard.errors import BadInput, exit_code_of
from nac_onboard.radio.channel import PRESETS, ChannelError, ChannelModel
from nac_onboard.radio.files import load_channel, save_channel
from tests.conftest import SHARED_DATA

CSV = SHARED_DATA / "forestfires.csv"


def hata(env: str) -> ChannelModel:
    return ChannelModel(name="t", path_loss=f"hata-{env}", freq_mhz=1200.0, bandwidth_hz=1e6, tx_power_dbm=20.0,
                        noise_w=1e-12, base_height_m=30.0, mobile_height_m=1.5)


@pytest.mark.parametrize("env, at_1km_db, at_10m_db", [
    # By hand: D = 69.55 + 26.16 lg1200 - 13.82 lg30 - a(1.5) = 129.660, E = 44.9 - 6.55 lg30 = 35.225.
    ("urban", 129.660, 59.211),
    ("large-city", 129.688, 59.239),  # a(h_m) = 3.2 (lg 17.625)^2 - 4.97 = -0.0008
    ("suburban", 118.933, 48.484),  # - 2 (lg(1200/28))^2 - 5.4 = -10.727
    ("rural", 99.841, 29.391),  # - 4.78 (lg1200)^2 + 18.33 lg1200 - 40.94 = -29.820
])
def test_hata_okumura_matches_hand_computed_losses(env, at_1km_db, at_10m_db):
    model = hata(env)
    assert model.path_loss_db(1000.0) == pytest.approx(at_1km_db, abs=0.005)
    assert model.path_loss_db(10.0) == pytest.approx(at_10m_db, abs=0.005)
    assert "extrapolation" in model.validity()


def test_free_space_log_distance_and_shannon_by_hand():
    fs = ChannelModel("fs", "free-space", 2437.0, 20e6, 0.0, 1e-12)
    assert fs.path_loss_db(10.0) == pytest.approx(60.187, abs=0.001)  # 20 + 187.737 - 147.55
    ld = ChannelModel("ld", "log-distance", 2437.0, 20e6, 10.0, 1e-12, exponent=3.0, ref_loss_db=40.0)
    assert ld.path_loss_db(10.0) == pytest.approx(70.0)
    assert ld.received_dbm(10.0) == pytest.approx(-60.0)
    # -60 dBm = 1e-9 W over 1e-12 W of noise: SNR 1000, C = 20 MHz * log2(1001) = 199.34 Mbit/s.
    assert ld.capacity_bps(10.0) == pytest.approx(199.3445e6, rel=1e-5)
    default_ref = ChannelModel("ld2", "log-distance", 2437.0, 20e6, 0.0, 1e-12, exponent=2.0)
    assert default_ref.path_loss_db(10.0) == pytest.approx(fs.path_loss_db(10.0)), "n = 2 from free space at 1 m"


def test_presets_behave_as_documented():
    wifi = PRESETS["wifi-flight"]
    assert 20.0 <= wifi.range_m() <= 25.0, "throughput falls to ~0 near 20-25 m, as in the flight tests"
    assert wifi.capacity_bps(9.8) > wifi.capacity_bps(12.8) > wifi.capacity_bps(17.0) > 0
    assert not wifi.in_range(30.0)
    paper = PRESETS["paper-sim"]
    assert (paper.freq_mhz, paper.bandwidth_hz, paper.noise_w) == (1200.0, 1200e6, 1.1e-35)
    assert paper.capacity_bps(9.43) > paper.capacity_bps(12.8) > paper.capacity_bps(17.0)


def test_channel_files_round_trip_and_errors_name_the_file(tmp_path):
    path = tmp_path / "calibrated.toml"
    save_channel(PRESETS["wifi-flight"], path)
    assert load_channel(str(path)) == PRESETS["wifi-flight"]
    (tmp_path / "bad.toml").write_text('path_loss = "log-distance"\nfreq_mhz = 2437\nbandwidth_hz = 2e7\n'
                                       'tx_power_dbm = 15\nnoise_w = 1e-12\ncolour = "red"\n')
    with pytest.raises(ChannelError, match="bad.toml: unknown key colour"):
        load_channel(str(tmp_path / "bad.toml"))
    with pytest.raises(ChannelError, match="not a preset"):
        load_channel("moon-link")
    with pytest.raises(ChannelError, match="path_loss must be one of"):
        ChannelModel("x", "three-ray", 2437.0, 20e6, 0.0, 1e-12)


def test_split_rows_equal_and_proportional():
    assert kernels.split_rows(100, [1, 1, 1]) == [(0, 33), (33, 67), (67, 100)]
    assert kernels.split_rows(517, [1, 1]) == [(0, 258), (258, 517)]
    assert kernels.split_rows(100, [3, 1]) == [(0, 75), (75, 100)]
    with pytest.raises(ValueError):
        kernels.split_rows(10, [0, 0])


def test_shard_gradients_combine_into_the_full_gradient():
    rng = np.random.default_rng(1)
    x, y, w = rng.standard_normal((50, 4)), rng.standard_normal(50), rng.standard_normal(4)
    full, full_cost, _ = kernels.combine_gradients([kernels.local_gradient(x, y, w)])
    parts = [kernels.local_gradient(x[a:b], y[a:b], w) for a, b in kernels.split_rows(50, [1, 2, 3])]
    gradient, cost, rows = kernels.combine_gradients(parts)
    assert rows == 50 and np.allclose(gradient, full, atol=1e-12) and cost == pytest.approx(full_cost)
    assert np.allclose(full, x.T @ (x @ w - y) / 50)
    partial, _, rows = kernels.combine_gradients(parts[:1])
    assert rows == len(parts[0][0]) * 0 + parts[0][2], "a missing shard: the others, weighted by their size"
    assert np.allclose(partial, parts[0][0] / parts[0][2])


def test_forest_fires_features_and_gradient_descent():
    x, y = forestfires.load(CSV)
    assert x.shape == (517, len(forestfires.FEATURES)) == (517, 30)
    assert np.allclose(x[:, 0], 1.0) and np.allclose(x[:, 1:11].mean(axis=0), 0, atol=1e-12)
    assert np.allclose(x[:, 1:11].std(axis=0), 1.0)
    assert np.all(x[:, 11:23].sum(axis=1) == 1) and np.all(x[:, 23:].sum(axis=1) == 1)
    assert y.min() == 0.0 and y.max() == pytest.approx(math.log1p(1090.84))
    _, costs = kernels.gradient_descent(x, y, np.zeros(30), 0.05, 200)
    assert all(b < a for a, b in zip(costs, costs[1:], strict=False))


def test_data_is_found_in_order_and_missing_data_is_explained(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("NAC_DATA_DIR", str(SHARED_DATA))
    assert forestfires.find_csv() == CSV
    assert forestfires.find_csv(str(CSV)) == CSV
    monkeypatch.setenv("NAC_DATA_DIR", str(tmp_path / "nowhere"))
    if SHARED_DATA.resolve() == forestfires.SOURCE_CHECKOUT_DATA.resolve():  # last: a checkout's ../shared/data
        assert forestfires.find_csv().resolve() == CSV.resolve()
    monkeypatch.setattr(forestfires, "SOURCE_CHECKOUT_DATA", tmp_path / "not-a-checkout")
    with pytest.raises(forestfires.DataError, match="nac-onboard data fetch"):
        forestfires.find_csv()
    with pytest.raises(forestfires.DataError, match="missing.csv"):
        forestfires.find_csv(str(tmp_path / "missing.csv"))


def test_malformed_csv_names_the_line(tmp_path):
    lines = CSV.read_text().splitlines()
    bad = tmp_path / "bad.csv"
    fields = lines[2].split(",")
    fields[2] = "smarch"
    bad.write_text("\n".join([lines[0], lines[1], ",".join(fields)]))
    with pytest.raises(forestfires.DataError, match=r"bad.csv: line 3: unknown month"):
        forestfires.load(bad)
    bad.write_text("\n".join([lines[0], lines[1] + ",7"]))
    with pytest.raises(forestfires.DataError, match="line 2: expected 13 fields, got 14"):
        forestfires.load(bad)


def test_fetch_takes_the_csv_out_of_the_archive_and_checks_its_hash(tmp_path):
    data = CSV.read_bytes()
    assert hashlib.sha256(data).hexdigest() == forestfires.CSV_SHA256
    for name, content in (("good.zip", data), ("tampered.zip", data.replace(b"mar", b"apr", 1))):
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as z:
            z.writestr("forestfires.names", "about")
            z.writestr("forestfires.csv", content)
        (tmp_path / name).write_bytes(buf.getvalue())
    stored = forestfires.fetch((tmp_path / "good.zip").as_uri(), dest_dir=tmp_path / "cache")
    assert stored.read_bytes() == data
    with pytest.raises(forestfires.DownloadError, match="expected 0d6586a1"):
        forestfires.fetch((tmp_path / "tampered.zip").as_uri(), dest_dir=tmp_path / "other")
    assert not (tmp_path / "other" / "forestfires.csv").exists()
    with pytest.raises(forestfires.DownloadError, match="cannot download") as refused:  # offline: exit 1, not 2
        forestfires.fetch((tmp_path / "absent.zip").as_uri(), dest_dir=tmp_path / "other")
    assert exit_code_of(refused.value) == 1


def test_scripted_distances_are_piecewise_constant():
    script = ScriptedDistances("iteration", {1: [(0, 10.0)], 2: [(0, 10.0), (50, 40.0), (80, 10.0)]})
    assert script.distances_m(49, 0.0) == {1: 10.0, 2: 10.0}
    assert script.distances_m(50, 0.0)[2] == 40.0 and script.distances_m(79, 0.0)[2] == 40.0
    assert script.distances_m(80, 0.0)[2] == 10.0


def test_core_binding_gives_the_master_its_own_core_when_ranks_share_cores():
    assert core_binding(2, cores=2) == "core" and core_binding(3, cores=4) == "core"
    assert core_binding(3, cores=2) == "user:0,1,1"
    assert core_binding(5, cores=3) == "user:0,1,2,1,2"
    assert core_binding(4, cores=1) == "core"


def test_each_host_gets_the_core_its_rank_would_be_bound_to():
    assert cpu_per_host(["m", "w1", "w2"], cores=2) == {"m": 0, "w1": 1, "w2": 1}
    assert cpu_per_host(["m", "w1"], cores=4) == {"m": 0, "w1": 1}
    assert cpu_per_host(["m", "w1"], cores=1) == {}


def test_the_job_gets_a_proxy_per_host_and_no_clean_up_that_kills_the_survivors(tmp_path):
    command = mpiexec_command(["m", "w1", "w2"], tmp_path, env={"A": "1"})
    assert "-disable-auto-cleanup" in command and command[command.index("-ppn") + 1] == "1"
    assert command[command.index("-n") + 1] == "3" and command[-3:] == ["-genv", "A", "1"]
    assert (tmp_path / "hostfile").read_text() == "m:1\nw1:1\nw2:1\n"
    launcher = (tmp_path / "launcher").read_text()
    assert "ip netns" not in launcher and os.access(tmp_path / "launcher", os.X_OK)
    mpiexec_command(["a", "b"], tmp_path, netns=True)
    assert "ip netns exec" in (tmp_path / "netns-launcher").read_text()


@pytest.mark.parametrize("hosts", [["m", "m"], ["m", "w 1"], ["m", "w1;reboot"], ["-x", "w1"]])
def test_host_names_that_would_break_the_launcher_are_refused(tmp_path, hosts):
    with pytest.raises(BadInput, match="MPI host"):
        mpiexec_command(hosts, tmp_path)


# ---- the Task contract, in one process ---------------------------------------------------------------------------
TOY_TASK = '''
"""A toy task, known to the job by this module alone: the sum of 0..9 times each iteration's input."""
import numpy as np

from nac_onboard.compute.task import Answer, Extra, Task


class Toy(Task):
    name, default_iterations, summary = "toy", 4, "sum of 0..9 times the input, blocks of rows among the workers"

    def __init__(self, options):
        super().__init__(options)
        self.data, self.block, self.totals = np.arange(10.0), None, []

    @classmethod
    def check(cls, options):
        pass

    def rows(self):
        return len(self.data)

    def input_floats(self):
        return 1

    def largest_input(self):
        return max(b - a for a, b in self.bounds) + 1

    def largest_result(self):
        return 1

    def take_block(self, rank):
        start, stop = self.bounds[rank - 1]
        self.block = self.data[start:stop]

    def work(self, payload, extra_rows=None):
        block, x = (self.block, payload) if extra_rows is None else (payload[:extra_rows], payload[extra_rows:])
        return Answer(np.array([block.sum() * x[0]]), len(block))

    def next_input(self, iteration):
        return np.array([iteration + 1.0])

    def plan_missing(self, iteration, payload, missing, answered):
        if not answered:
            return []
        return [Extra(answered[0], r, np.concatenate([self.data[slice(*self.bounds[r - 1])], payload]),
                      self.bounds[r - 1][1] - self.bounds[r - 1][0]) for r in missing]

    def combine(self, iteration, payload, answers):
        rows = sum(a.rows for a in answers.values())
        total = float(sum(a.values[0] for a in answers.values()))
        self.totals.append(total)
        return {"total": total, "complete": rows == len(self.data)}

    def results(self):
        return {"totals": np.array(self.totals)}
'''


class _FakeRequest:
    def __init__(self, done: bool = False):
        self.done, self.count = done, 0

    def Test(self):  # noqa: N802 (mpi4py's names)
        return self.done

    def Cancel(self):  # noqa: N802
        self.done = True


class FakeMPI:
    """Just what the runner uses of mpi4py, between threads of one process: sends are delivered at once, in order
    (as MPI keeps the order of one sender's messages), into the receiver's earliest matching posted receive."""

    DOUBLE, UNDEFINED = "double", -32766
    REQUEST_NULL = _FakeRequest(done=True)

    class Exception(Exception):  # noqa: N818 (mpi4py's name)
        pass

    class Status:
        count = 0

        def Get_count(self, datatype):  # noqa: N802
            return self.count

    class Request:
        @staticmethod
        def Testany(requests, status):  # noqa: N802
            for k, request in enumerate(requests):
                if request is not FakeMPI.REQUEST_NULL and request.done:
                    status.count = request.count
                    return k, True
            return FakeMPI.UNDEFINED, False

        @staticmethod
        def Waitall(requests):  # noqa: N802
            pass


class FakeWorld:
    def __init__(self, size: int, drop=lambda dest, message: False):
        self.size, self.drop = size, drop  # drop(dest, message): lose this message on the way
        self.lock, self.posted, self.queued = threading.Lock(), [], []
        self.shared, self.broadcast = None, threading.Event()

    def comm(self, rank: int) -> "FakeComm":
        return FakeComm(self, rank)

    def deliver(self, source: int, dest: int, tag: int, data: np.ndarray) -> None:
        if self.drop(dest, data):
            return
        with self.lock:
            for item in self.posted:
                owner, want_source, want_tag, buf, request = item
                if (owner, want_source, want_tag) == (dest, source, tag) and not request.done:
                    self.posted.remove(item)
                    self._fill(buf, request, data)
                    return
            self.queued.append((source, dest, tag, data.copy()))

    @staticmethod
    def _fill(buf: np.ndarray, request: _FakeRequest, data: np.ndarray) -> None:
        assert len(data) <= len(buf), f"a {len(data)}-float message into a {len(buf)}-float receive (MPI: truncate)"
        buf[:len(data)] = data
        request.count, request.done = len(data), True

    def post(self, owner: int, source: int, tag: int, buf: np.ndarray) -> _FakeRequest:
        request = _FakeRequest()
        with self.lock:
            for item in self.queued:
                if item[:3] == (source, owner, tag):
                    self.queued.remove(item)
                    self._fill(buf, request, item[3])
                    return request
            self.posted.append((owner, source, tag, buf, request))
        return request


class FakeComm:
    def __init__(self, world: FakeWorld, rank: int):
        self.world, self.rank = world, rank

    def Get_rank(self):  # noqa: N802
        return self.rank

    def Get_size(self):  # noqa: N802
        return self.world.size

    def bcast(self, obj, root=0):
        if self.rank == root:
            self.world.shared = obj
            self.world.broadcast.set()
            return obj
        assert self.world.broadcast.wait(10.0)
        return self.world.shared

    def Irecv(self, spec, source, tag):  # noqa: N802
        return self.world.post(self.rank, source, tag, spec[0])

    def Isend(self, spec, dest, tag):  # noqa: N802
        self.world.deliver(self.rank, dest, tag, spec[0])
        return _FakeRequest(done=True)

    def Send(self, spec, dest, tag):  # noqa: N802
        self.world.deliver(self.rank, dest, tag, spec[0])

    def Abort(self, code):  # noqa: N802
        raise RuntimeError(f"rank {self.rank} aborted ({code})")


@pytest.fixture
def toy_task(tmp_path, monkeypatch):
    """The toy task's module in a folder of its own, added to where the job looks for tasks: nothing else knows it."""
    from nac_onboard.compute import tasks

    folder = tmp_path / "more_tasks"
    folder.mkdir()
    (folder / "toy.py").write_text(TOY_TASK)
    monkeypatch.setattr(tasks, "__path__", [*tasks.__path__, str(folder)])
    yield
    sys.modules.pop(f"{tasks.__name__}.toy", None)


class RecordingLog:
    """The master's log in memory: each record as the runner wrote it (kind by name)."""

    def __init__(self):
        self.records: list[dict] = []

    def write(self, kind, t_s=None, **fields) -> dict:
        record = {"t_s": t_s, "kind": getattr(kind, "name", kind), **fields}
        self.records.append(record)
        return record


def run_job(options, drop=lambda dest, message: False) -> tuple[int, list[dict]]:
    """The runner's real master and workers, each rank a thread, over FakeMPI; (exit code, the master's records)."""
    from nac_onboard.compute.runner import Master, run_worker

    size = 4
    world = FakeWorld(size, drop)
    workers = [threading.Thread(target=run_worker, args=(world.comm(r), FakeMPI, options, RecordingLog()),
                                daemon=True) for r in range(1, size)]
    for thread in workers:
        thread.start()
    log = RecordingLog()
    code = Master(world.comm(0), FakeMPI, options, log).run()
    for thread in workers:
        thread.join(10.0)
        assert not thread.is_alive(), "every worker stopped"
    return code, log.records


def test_a_new_task_is_one_module_and_the_runner_sends_collects_and_resends_for_it(toy_task, tmp_path):
    from nac_onboard.compute.options import build_parser, options_from_argv
    from nac_onboard.compute.tasks import all_tasks

    assert "toy" in all_tasks() and "toy: sum of 0..9" in " ".join(build_parser().format_help().split())
    options = options_from_argv(["--task", "toy", "--out", str(tmp_path), "--timeout-s", "0.3",
                                 "--idle-timeout-s", "10"])
    assert options.iterations == 4, "its default"
    # Rank 3's input of iteration 2 is lost: its block [7, 10) is sent again, to rank 1, and arrives.
    lost = lambda dest, message: dest == 3 and message[0] == KIND_WORK and message[1] == 2  # noqa: E731
    code, written = run_job(options, drop=lost)
    assert code == 0
    started, *its, summary = [r for r in written if r["kind"] in ("run_started", "iteration", "run_summary")]
    assert started["shards"] == [(0, 3), (3, 7), (7, 10)] and started["task"] == "toy"
    assert [r["total"] for r in its] == [45.0 * (k + 1) for k in range(4)] and all(r["complete"] for r in its)
    assert [r.get("reassigned") for r in its] == [None, None, [{"rows_of": 3, "by": 1}], None]
    assert its[2]["workers"]["absent"] == [None, None, "timeout"]
    assert summary["iterations"] == summary["complete_iterations"] == 4
    assert summary["absent_iterations"] == {"1": 0, "2": 0, "3": 1}
    assert list(np.load(tmp_path / "results.npz")["totals"]) == [45.0, 90.0, 135.0, 180.0]


def drive(task_class, options, blocks: int, lost: frozenset = frozenset()):
    """One iteration of the contract as the runner drives it, without MPI: a task per worker, one for the master;
    the blocks of the `lost` ranks do not arrive and the master's plan for them is worked by the ranks it names."""
    bounds = kernels.split_rows(task_class(options).rows(), [1.0] * blocks)
    workers = {}
    for rank in range(1, blocks + 1):
        workers[rank] = task_class(options)
        workers[rank].split(bounds)
        workers[rank].take_block(rank)
    master = task_class(options)
    master.split(bounds)
    payload = master.next_input(0)
    answers = {r: w.work(payload.copy()) for r, w in workers.items() if r not in lost}
    plan = master.plan_missing(0, payload, sorted(lost), sorted(answers)) if lost else []
    for extra in plan:
        assert extra.payload.size <= master.largest_input()
        answers[extra.rows_of] = workers[extra.by].work(extra.payload, extra.rows)
    assert all(a.values.size <= master.largest_result() for a in answers.values())
    return master, payload, plan, master.combine(0, payload, answers)


def test_matmul_stacks_the_blocks_and_plans_the_missing_rows_for_the_workers_that_answered(tmp_path):
    from nac_onboard.compute.tasks.matmul import Matmul, matmul_inputs

    options = ComputeOptions(task="matmul", iterations=1, duration_s=None, out=str(tmp_path), m=10, n=6, l=2,
                             on_missing="reassign", save_results=True)
    master, payload, plan, record = drive(Matmul, options, 3, lost=frozenset({2, 3}))
    assert record == {"complete": True} and [(e.by, e.rows_of, e.rows) for e in plan] == [(1, 2, 4), (1, 3, 3)]
    a = matmul_inputs(0, 10, 6)
    assert np.allclose(master.results()["C_0"], a @ payload.reshape(6, 2))
    incomplete = dataclasses.replace(options, on_missing="incomplete")
    _, _, plan, record = drive(Matmul, incomplete, 3, lost=frozenset({2}))
    assert plan == [] and record == {"complete": False}


def test_linreg_steps_on_the_shards_that_arrived(tmp_path):
    from nac_onboard.compute.tasks.linreg import Linreg

    options = ComputeOptions(task="linreg", iterations=1, duration_s=None, out=str(tmp_path), data=str(CSV))
    master, payload, plan, record = drive(Linreg, options, 2)
    x, y = forestfires.load(CSV)
    w, costs = kernels.gradient_descent(x, y, np.zeros(x.shape[1]), 0.05, 1)
    assert plan == [] and record["rows_used"] == 517 and record["complete"]
    assert record["cost"] == pytest.approx(costs[0], rel=1e-12) and np.allclose(master.results()["weights"], w)
    master, _, _, record = drive(Linreg, options, 2, lost=frozenset({2}))
    assert record["rows_used"] == 258 and not record["complete"]
    _, _, _, record = drive(Linreg, options, 2, lost=frozenset({1, 2}))
    assert record == {"cost": None, "rows_used": 0, "complete": False}


def test_the_planned_links_are_the_model_median_whenever_the_plan_is_made(tmp_path):
    """--allocation capacity's expected rate at a distance is the channel's median rate (rate adaptation settled,
    no shadowing or fading draw) however long after the last plan, and at which distance, it is made: a stateful
    look made a plan depend on the time since the last one (a clean-clone run re-planned the same positions)."""
    channel = PRESETS["wifi-flight"]
    assert channel.rate_adaptation_s > 0 and channel.shadowing_sigma_db > 0
    options = ComputeOptions(task="linreg", iterations=1, duration_s=None, out=str(tmp_path), channel=channel,
                             allocation="capacity")
    planner = Planner(options, [1, 2], task=None, source=None)
    out_of_range_m = channel.range_m() + 10.0
    assert planner.expected_rates_bps({1: 8.0, 2: out_of_range_m}) == [channel.capacity_bps(8.0), 0.0]
    for _ in range(3):  # back in range at once: no lag from the out-of-range look
        assert planner.expected_rates_bps({1: 8.0, 2: 16.0}) == [channel.capacity_bps(8.0), channel.capacity_bps(16.0)]
    assert planner.expected_rates_bps({2: 16.0}) == [None, channel.capacity_bps(16.0)]
