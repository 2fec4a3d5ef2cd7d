"""Options of `nac-onboard compute`, parsed and checked before MPI does anything (bad input: exit 2 on every rank)."""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field

from nac_onboard.clock import Clock, from_env
from nac_onboard.compute.checkpoint import load_checkpoint
from nac_onboard.compute.device import HOST, DeviceProfile, load_device_profile
from nac_onboard.compute.positions import (
    FeedDistances,
    FixedDistances,
    PositionsError,
    ScriptedDistances,
    wait_for_feed,
)
from nac_onboard.compute.task import Task
from nac_onboard.compute.tasks import all_tasks
from nac_onboard.errors import BadInput, NacError
from nac_onboard.inputs import (
    MAX_AUTOPILOT_LOG_BYTES,
    MAX_CONFIG_BYTES,
    check_id,
    check_regular_file,
    number_arg,
    parse_number,
)
from nac_onboard.radio.channel import PRESETS, ChannelModel
from nac_onboard.radio.files import load_channel
from nac_onboard.records import kinds


@dataclass(frozen=True)
class ComputeOptions:
    task: str  # a name from nac_onboard.compute.tasks
    iterations: int | None
    duration_s: float | None
    out: str
    end_at_s: float | None = None  # on the run's clock
    start_file: str | None = None
    seed: int = 0
    m: int = 100
    n: int = 10000
    l: int = 1  # noqa: E741 (the research's name for B's columns)
    a_path: str | None = None
    data: str | None = None
    learning_rate: float = 0.05
    emulate: str = "none"
    channel: ChannelModel = PRESETS["paper-sim"]  # loaded once, from --channel
    positions: str = "none"
    distances: tuple[float, ...] = ()
    positions_script: str | None = None
    feed: str = "127.0.0.1:47200"
    vehicles: tuple[str, ...] = ()
    fleet_workers: tuple[str, ...] = ()  # every worker of the fleet in order: a rank's log is named by its place here
    timeout_s: float = 5.0
    idle_timeout_s: float = 600.0
    on_missing: str = "incomplete"
    allocation: str = "equal"
    energy_wh: tuple[float, ...] = ()  # --allocation energy: each worker's companion energy left, rank order
    code_k: int = 0  # matmul_mds: results that decode (0: the workers less one)
    code_s: int = 1  # linreg_gc: stragglers tolerated
    code_redundancy: float = 1.5  # matmul_bpcc: coded units over data blocks
    batch_units: int = 1  # matmul_bpcc: coded units per batch sent back
    replan_every: int = 0  # re-plan every this many iterations and on absences (0: the start's blocks stay)
    link_rates: str = "model"  # what the allocation expects of each link: the channel model, or the latest probes
    save_results: bool = False
    checkpoint_s: float = 10.0  # results.npz rewritten (atomically) this often while the job runs; 0 = at the end
    resume: bool = False  # a restarted master: continue from the checkpoint in --out
    pad_bits: float = 0.0  # zeros appended to every message: the channel's overhead as real bytes (kernel network)
    probe_backlog_packets: float = 0.0  # sleep: what the probes alongside keep in the master's transmit queue
    device: DeviceProfile = HOST  # the companion's CPU: each rank's work takes its time on the run's clock
    device_of: tuple[tuple[str, DeviceProfile], ...] = ()  # (vehicle, profile): a companion other than the rest
    clock: Clock = field(default_factory=Clock)  # $NAC_SIM_CLOCK in SITL: times below are simulated seconds

    @property
    def task_class(self) -> type[Task]:
        return all_tasks()[self.task]

    def vehicle_of(self, rank: int) -> str:
        return self.vehicles[rank] if rank < len(self.vehicles) else f"rank{rank}"

    def log_number(self, rank: int) -> int:
        """The N of a worker's rank-N.jsonl: its place among --fleet-workers, so a job restarted without a lost
        worker (its ranks numbered again) keeps each vehicle's records in one file; the rank without them."""
        vehicle = self.vehicle_of(rank)
        return self.fleet_workers.index(vehicle) + 1 if vehicle in self.fleet_workers else rank

    def device_for(self, rank: int) -> DeviceProfile:
        """Rank `rank`'s companion: its own profile (--device-of), else the fleet's (--device)."""
        return dict(self.device_of).get(self.vehicle_of(rank), self.device)


MAX_ITERATIONS = 10_000_000
PROBE_MAX_AGE_S = 30.0  # simulated seconds: three of the fleet config's probe periods (deploy/master.toml: 10 s)
MAX_DURATION_S = 7 * 86400.0  # a week: far beyond any battery
_size = number_arg(1, 10_000_000, integer=True)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):
        raise BadInput(message)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="nac-onboard compute", description=__doc__)
    tasks = all_tasks()
    p.add_argument("--task", choices=list(tasks), required=True,
                   help="; ".join(f"{name}: {cls.summary}" for name, cls in tasks.items()))
    stop = p.add_mutually_exclusive_group()
    stop.add_argument("--iterations", type=number_arg(1, MAX_ITERATIONS, integer=True),
                      help="iterations to run (default: " + ", ".join(
        f"{cls.default_iterations} for {name}" for name, cls in tasks.items()) + ")")
    stop.add_argument("--duration-s", type=number_arg(0, MAX_DURATION_S, low_open=True, unit="s"),
                      help="run this long instead of a fixed number of iterations")
    stop.add_argument("--end-at-s", type=number_arg(0, 1e11, unit="s"),
                      help="run until this time on the run's clock (unix time; simulated seconds in SITL)")
    p.add_argument("--start-file", help="after setting up, wait until this file exists before the first iteration "
                                        "(an orchestrator's go: the vehicles are in the air); a JSON object in it "
                                        "may give end_at_s, as --end-at-s does")
    p.add_argument("--out", default="compute-out",
                   help=f"directory for {kinds.COMPUTE_LOG.name} (and {kinds.RESULTS.name})")
    p.add_argument("--seed", type=number_arg(0, 2**32 - 1, integer=True), default=0)
    p.add_argument("--m", type=_size, default=100, help="matmul: rows of A")
    p.add_argument("--n", type=_size, default=10000, help="matmul: columns of A, rows of B")
    p.add_argument("--l", type=_size, default=1, help="matmul: columns of B")
    p.add_argument("--a", dest="a_path", help="matmul: A from this .npy file (every rank reads it) instead of the seed")
    p.add_argument("--data", help="linreg: forestfires.csv (default $NAC_DATA_DIR, then the user cache)")
    p.add_argument("--learning-rate", type=number_arg(0, 1000, low_open=True), default=0.05)
    p.add_argument("--emulate", choices=["none", "sleep"], default="none",
                   help="sleep: delay each transfer by bits / capacity (SITL); none: the network is real")
    p.add_argument("--channel", default="paper-sim", help="channel preset (paper-sim, wifi-flight) or TOML file")
    p.add_argument("--positions", choices=["none", "fixed", "script", "feed"], default="none")
    p.add_argument("--distances", help="fixed: metres from the master, one per worker, comma-separated")
    p.add_argument("--positions-script", help="script: JSON file of distances by iteration or time")
    p.add_argument("--feed", default="127.0.0.1:47200", help="feed: the local agent's state feed")
    p.add_argument("--vehicles", help="feed: vehicle ids in rank order, master first (comma-separated)")
    p.add_argument("--fleet-workers", help="every worker of the fleet, in order, when this job has only some of "
                                           "them (a restart without a lost companion): worker logs keep their "
                                           "numbers (comma-separated ids)")
    p.add_argument("--timeout-s", type=number_arg(0, 86400, low_open=True, unit="s"), default=5.0,
                   help="how long the master waits for an iteration's results")
    p.add_argument("--idle-timeout-s", type=number_arg(0, 7 * 86400, low_open=True, unit="s"), default=600.0,
                   help="a worker that hears nothing this long aborts")
    p.add_argument("--on-missing", choices=["incomplete", "reassign"], default="incomplete",
                   help="matmul: a worker's rows that did not arrive are re-assigned or the iteration is incomplete")
    p.add_argument("--allocation", choices=["equal", "capacity", "speed", "energy"], default="equal",
                   help="capacity: blocks in proportion to each link's predicted capacity (the channel model at the "
                        "positions); speed: to each worker's expected rows per second (its device's CPU per row and "
                        "its link's time per row of result: BPCC's allocation); energy: to each worker's companion "
                        "energy left (--energy-wh)")
    p.add_argument("--link-rates", choices=["model", "probes"], default="model",
                   help="what --allocation capacity|speed expects of each link: the channel model at the positions, "
                        "or (in flight) the master's agent's latest probe to that worker, the model where none is "
                        f"fresher than {PROBE_MAX_AGE_S:g} s (--positions feed)")
    p.add_argument("--replan-every", type=number_arg(0, MAX_ITERATIONS, integer=True), default=0,
                   help="re-plan the blocks from the live links every this many iterations (0: at the start only); "
                        "with any allocation, a worker absent or unresponsive is planned out until it is back")
    p.add_argument("--energy-wh", help="--allocation energy: each worker's companion energy left (Wh), in rank "
                                       "order, comma-separated")
    p.add_argument("--code-k", type=number_arg(0, 10_000, integer=True), default=0,
                   help="matmul_mds: how many of the workers' coded results decode A B (0: the workers less one)")
    p.add_argument("--code-s", type=number_arg(0, 10_000, integer=True), default=1,
                   help="linreg_gc: stragglers the gradient code tolerates (each worker holds s + 1 shards)")
    p.add_argument("--code-redundancy", type=number_arg(1, 10), default=1.5,
                   help="matmul_bpcc: coded units per data block (U = ceil(r k) units, any k decode)")
    p.add_argument("--batch-units", type=number_arg(1, 10_000, integer=True), default=1,
                   help="matmul_bpcc: coded units a worker multiplies before sending their products back")
    p.add_argument("--save-results", action="store_true", help="matmul: keep every B and A@B in results.npz")
    p.add_argument("--checkpoint-s", type=number_arg(0, 86400, unit="s"), default=10.0,
                   help="rewrite results.npz this often while running (0: only at the end)")
    p.add_argument("--resume", action="store_true",
                   help="a restarted master: continue the iteration count and the task's state (linreg's weights) "
                        "from the checkpoint in --out; --iterations is then the total")
    p.add_argument("--pad-bits", type=number_arg(0, 1e9, unit="bits"), default=0.0,
                   help="append this many bits of zeros to every message (a transfer's overhead, as real bytes)")
    p.add_argument("--probe-backlog-packets", type=number_arg(0, 100_000, unit="packets"), default=0.0,
                   help="sleep: the packets the probes alongside the job keep in the master's transmit queue (a "
                        "frame-level air's scenario on the sleep network): each round of inputs waits for them to "
                        "leave at the links' rates")
    p.add_argument("--device", default="host",
                   help="the companion's CPU: 'host' (this machine's speed), a shipped profile (jetson-tx2, "
                        "jetson-xavier-nx, jetson-orin-nano, jetson-orin-nx) or a device profile TOML ([device] name, "
                        "source, slowdown or cpu_score_mips): each rank's work then takes that device's time")
    p.add_argument("--device-of", action="append", default=[], metavar="VEHICLE=PROFILE",
                   help="one companion's own device profile (repeatable): a slow companion among the rest")
    return p


def parse_args(argv: list[str] | None = None) -> ComputeOptions:
    """options_from_argv for a rank's main: bad input prints one line and exits 2 on every rank."""
    try:
        return options_from_argv(argv)
    except NacError as err:
        print(f"nac-onboard compute: {err}", file=sys.stderr)
        raise SystemExit(err.exit_code) from None


def options_from_argv(argv: list[str] | None) -> ComputeOptions:
    """Parsed and checked options (task options and data included); BadInput says what is wrong."""
    args = build_parser().parse_args(argv)
    task = all_tasks()[args.task]
    iterations = args.iterations
    if iterations is None and args.duration_s is None and args.end_at_s is None:
        iterations = task.default_iterations
    if args.checkpoint_s < 0:
        raise BadInput("--checkpoint-s must be >= 0")
    if not 0 <= args.pad_bits <= 1e9:
        raise BadInput("--pad-bits must be between 0 and 1e9")
    if args.timeout_s <= 0 or args.idle_timeout_s <= 0:
        raise BadInput("--timeout-s and --idle-timeout-s must be > 0")
    distances = tuple(parse_number(d, "--distances", 0, 1e6, unit="m") for d in args.distances.split(",")) \
        if args.distances else ()
    vehicles = tuple(check_id(v.strip(), "--vehicles") for v in args.vehicles.split(",")) if args.vehicles else ()
    fleet_workers = tuple(check_id(v.strip(), "--fleet-workers") for v in args.fleet_workers.split(",")) \
        if args.fleet_workers else ()
    energy_wh = tuple(parse_number(e, "--energy-wh", 0, 1e6, low_open=True, unit="Wh")
                      for e in args.energy_wh.split(",")) if args.energy_wh else ()
    if (args.allocation == "energy") != bool(energy_wh):
        raise BadInput("--allocation energy and --energy-wh W1,W2,... (one per worker) go together")
    options = ComputeOptions(
        task=args.task, iterations=iterations, duration_s=args.duration_s, end_at_s=args.end_at_s,
        start_file=args.start_file, out=args.out, seed=args.seed, m=args.m,
        n=args.n, l=args.l, a_path=args.a_path, data=args.data, learning_rate=args.learning_rate,
        emulate=args.emulate, channel=load_channel(args.channel), positions=args.positions, distances=distances,
        positions_script=args.positions_script, feed=args.feed, vehicles=vehicles, fleet_workers=fleet_workers,
        timeout_s=args.timeout_s, idle_timeout_s=args.idle_timeout_s, on_missing=args.on_missing,
        allocation=args.allocation,
        energy_wh=energy_wh, code_k=args.code_k, code_s=args.code_s, code_redundancy=args.code_redundancy,
        batch_units=args.batch_units, replan_every=args.replan_every, link_rates=args.link_rates,
        device_of=device_of(args.device_of),
        save_results=args.save_results, checkpoint_s=args.checkpoint_s, resume=args.resume, pad_bits=args.pad_bits,
        probe_backlog_packets=args.probe_backlog_packets,
        device=HOST if args.device == "host" else load_device_profile(args.device), clock=from_env())
    for option, path, what, limit in [("--a", options.a_path, "matrix A (.npy)", MAX_AUTOPILOT_LOG_BYTES),
                                      ("--data", options.data, "data set (CSV)", MAX_AUTOPILOT_LOG_BYTES),
                                      ("--positions-script", options.positions_script, "positions script",
                                       MAX_CONFIG_BYTES)]:
        if path is not None:  # regular and bounded before numpy, pandas or json open it
            check_regular_file(path, f"{option} {what}", limit)
    if options.link_rates == "probes" and options.positions != "feed":
        raise BadInput("--link-rates probes reads the agent's probes through its state feed: --positions feed")
    if options.probe_backlog_packets and options.emulate != "sleep":
        raise BadInput("--probe-backlog-packets models a queue for --emulate sleep; on a real network the queue is "
                       "the network's own")
    if options.emulate == "sleep" and options.positions == "none":
        raise BadInput("--emulate sleep needs positions: --positions fixed|script|feed")
    task.check(options)
    if options.resume:  # every rank refuses a missing or foreign checkpoint before MPI starts
        iteration, _ = load_checkpoint(options.out, options.task, arrays=False)
        if options.iterations is not None and iteration >= options.iterations:
            raise BadInput(f"--resume: the checkpoint in {options.out} is at iteration {iteration}, already "
                           f"--iterations {options.iterations}")
    if options.positions != "feed":  # the feed is asked once MPI runs, on the master only
        build_source(options)
    return options


def device_of(values: list[str]) -> tuple[tuple[str, DeviceProfile], ...]:
    """--device-of VEHICLE=PROFILE values, each profile loaded and checked."""
    out = []
    for value in values:
        vehicle, sep, path = value.partition("=")
        if not sep or not path:
            raise BadInput(f"--device-of {value!r}: expected VEHICLE=PROFILE (a device profile TOML)")
        out.append((check_id(vehicle.strip(), "--device-of"), load_device_profile(path)))
    return tuple(out)


def build_source(options: ComputeOptions, wait_s: float = 30.0):
    if options.positions == "fixed":
        if not options.distances:
            raise PositionsError("--positions fixed needs --distances D1,D2,... (one per worker)")
        return FixedDistances(list(options.distances))
    if options.positions == "script":
        if not options.positions_script:
            raise PositionsError("--positions script needs --positions-script FILE")
        return ScriptedDistances.load(options.positions_script)
    if options.positions == "feed":
        source = FeedDistances(options.feed, list(options.vehicles))
        wait_for_feed(source, wait_s)
        return source
    return None
