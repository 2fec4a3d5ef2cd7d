"""`nac-onboard`: the companion computer's command line.

    nac-onboard agent --config FILE [--run-id ID] [--log-dir DIR]   the daemon (systemd runs this)
    nac-onboard throughput server [--bind ADDR] [--port N]           like `iperf3 -s`
    nac-onboard throughput probe HOST [--port N] [-t S | -n BYTES]   like `iperf3 -c HOST -J`
    nac-onboard log check FILE...                                   read flight logs, report damaged lines
    nac-onboard state [--feed HOST:PORT]                             what the agent knows of everyone now
    nac-onboard compute --task matmul|linreg ...                     one MPI rank (run under mpiexec)
    nac-onboard bench --task T [--workers N] [--device-ms MS]        the job's CPU per iteration (device profiles)
    nac-onboard data fetch [--url URL]                               the Forest Fires CSV into the user cache
    nac-onboard doctor [--role R] [--config FILE] [--json]           what this node has, and what its role lacks
    nac-onboard mpi hostfile [--feed HOST:PORT] [--out FILE]         MPICH hostfile from the peers the agent hears
    nac-onboard mpi run [--hostfile FILE] -- PROGRAM ARGS...         the job over them, same MPI build checked
    nac-onboard mpi run --keep-going -- nac-onboard compute ...      ... started again when a companion is lost or back

Exit codes: 0 ok, 1 the operation failed, 2 bad input.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import platform
import sys

from nac_onboard.agent.config import load_agent_config
from nac_onboard.errors import BadInput, OperationFailed, run_cli
from nac_onboard.inputs import check_name, name_arg, number_arg
from nac_onboard.link.throughput import DEFAULT_PORT


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nac-onboard", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("-v", "--verbose", action="store_true")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    agent = sub.add_parser("agent", help="run the onboard agent")
    agent.add_argument("--config", required=True, help="agent TOML file (see deploy/)")
    agent.add_argument("--run-id", type=name_arg,
                       help="run directory name (default: log.run_id, $NAC_RUN_ID or the start time)")
    agent.add_argument("--log-dir", help="override log.dir")

    tp = sub.add_parser("throughput", help="iperf3-style throughput server and probe")
    tsub = tp.add_subparsers(dest="action", required=True, metavar="ACTION")
    server = tsub.add_parser("server", help="serve probes until interrupted")
    server.add_argument("--bind", default="0.0.0.0")
    server.add_argument("--port", type=int, default=DEFAULT_PORT)
    client = tsub.add_parser("probe", help="measure the path to a server; prints iperf3-shaped JSON")
    client.add_argument("host")
    client.add_argument("--port", type=int, default=DEFAULT_PORT)
    amount = client.add_mutually_exclusive_group()
    amount.add_argument("-t", "--time", type=float, default=None, dest="duration_s", help="seconds (default 1)")
    amount.add_argument("-n", "--bytes", type=int, default=None, dest="nbytes")
    client.add_argument("-i", "--interval", type=float, default=0.5, dest="interval_s")
    client.add_argument("-b", "--bitrate", type=float, default=None, dest="rate_bps", help="cap, bits/s")

    logs = sub.add_parser("log", help="flight log tools")
    lsub = logs.add_subparsers(dest="action", required=True, metavar="ACTION")
    lsub.add_parser("check", help="parse JSON Lines logs and report damaged lines").add_argument("files", nargs="+")

    state = sub.add_parser("state", help="ask the local agent for everyone's position")
    state.add_argument("--feed", default="127.0.0.1:47200")
    sub.add_parser("compute", help="one rank of the MPI job: mpiexec -n N+1 -bind-to core nac-onboard compute ... "
                                   "(see nac-onboard compute --help)", add_help=False)
    bench = sub.add_parser("bench", help="CPU time per iteration of the job's own work on this machine (no MPI, no "
                                         "network): run it here and on the companion; the ratio is a device "
                                         "profile's slowdown")
    bench.add_argument("--task", required=True, help="a task of the MPI job (linreg, matmul: nac-onboard compute's)")
    bench.add_argument("--workers", type=number_arg(1, 1000, integer=True), default=3,
                       help="the job's workers: the data is split into this many blocks (default: %(default)s)")
    bench.add_argument("--seconds", type=number_arg(0.1, 600, unit="s"), default=5.0, dest="seconds")
    bench.add_argument("--data", help="linreg: forestfires.csv (default $NAC_DATA_DIR, then the user cache)")
    bench.add_argument("--device-ms", type=number_arg(0, 1e6, low_open=True, unit="ms"), dest="device_ms",
                       help="the figure this command printed on the companion: prints the slowdown for its profile")
    sub.add_parser("cpu-score", help="measure this machine's single-thread CPU score (7z b -mmt1, sbc-bench's "
                                     "method, about a minute) and keep it: shipped device profiles compare against it")
    data = sub.add_parser("data", help="the Forest Fires data set")
    dsub = data.add_subparsers(dest="action", required=True, metavar="ACTION")
    fetch = dsub.add_parser("fetch", help="download the UCI archive, check the CSV's sha256, keep it in the cache")
    fetch.add_argument("--url", default=None, help="archive URL (default: the UCI repository's)")
    doctor = sub.add_parser("doctor", help="what this node has (Python, MPI, glibc, clock, serial port, disk) "
                                           "and whether its role can run; exit 1 naming what is missing")
    doctor.add_argument("--role", choices=("master", "worker"), help="default: the config's, else worker")
    doctor.add_argument("--config", help="agent TOML: its autopilot serial port and log directory are checked")
    doctor.add_argument("--json", action="store_true")
    mpi = sub.add_parser("mpi", help="an MPI job over the vehicles the master's agent hears")
    msub = mpi.add_subparsers(dest="action", required=True, metavar="ACTION")
    hostfile = msub.add_parser("hostfile", help="write MPICH's hostfile: this master, then the live workers; "
                                                "exit 2 naming a node whose MPI build differs")
    hostfile.add_argument("--feed", default="127.0.0.1:47200", help="the master agent's state feed")
    hostfile.add_argument("--out", help="file to write (default: print it)")
    job = msub.add_parser("run", help="check the MPI builds, write the hostfile, run mpiexec -f HOSTFILE -n N ...")
    job.add_argument("--feed", default="127.0.0.1:47200", help="the master agent's state feed")
    job.add_argument("--hostfile", default="mpi-hostfile", help="where to write the hostfile (default: %(default)s)")
    job.add_argument("--timeout", type=float, default=None, dest="timeout_s", help="seconds before giving up")
    job.add_argument("--keep-going", action="store_true",
                     help="nac-onboard compute only: start the job again from its checkpoint when a companion is "
                          "lost (with the workers heard) or back (with it), until it ends (docs/compute.md)")
    job.add_argument("program", nargs=argparse.REMAINDER, help="-- then the program and its arguments")
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["compute"]:  # its own parser, shared with `python -m nac_onboard.compute`
        from nac_onboard.compute.runner import main as compute_main

        return compute_main(argv[1:])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(message)s")
    return run_cli("nac-onboard", lambda: run(args))


def run(args) -> int:
    if args.command == "agent":
        return agent_command(args)
    if args.command == "throughput":
        return throughput_command(args)
    if args.command == "log":
        return log_check(args.files)
    if args.command in ("doctor", "mpi"):
        from nac_onboard.node import commands

        if args.command == "doctor":
            return commands.run_doctor(args.role, args.config, args.json)
        if args.action == "hostfile":
            return commands.write_hostfile(args.feed, args.out)
        program = args.program[1:] if args.program[:1] == ["--"] else args.program
        if args.keep_going:
            return commands.run_kept_job(args.feed, args.hostfile, program, args.timeout_s)
        return commands.run_job(args.feed, args.hostfile, program, args.timeout_s)
    if args.command == "bench":
        return bench_command(args)
    if args.command == "cpu-score":
        return cpu_score_command()
    if args.command == "data":
        from nac_onboard.compute import forestfires

        path = forestfires.fetch(args.url or forestfires.UCI_ARCHIVE_URL)
        print(f"stored {path} (sha256 {forestfires.CSV_SHA256})")
        return 0
    from nac_onboard.agent.state_feed import fetch_state

    print(json.dumps(fetch_state(args.feed), indent=2))
    return 0


def bench_command(args) -> int:
    from nac_onboard.compute.device import SLOWDOWN_RANGE, bench
    from nac_onboard.compute.options import options_from_argv

    options = options_from_argv(["--task", args.task] + (["--data", args.data] if args.data else []))
    result = bench(options, args.workers, args.seconds)
    print(f"{result.task}, {result.workers} workers: {result.cpu_s * 1e3:.4g} ms CPU per iteration "
          f"(master {result.master_cpu_s * 1e3:.3g} ms, one worker {result.worker_cpu_s * 1e3:.3g} ms; "
          f"{result.iterations} iterations) on {platform.node()} ({platform.machine()}, Python "
          f"{platform.python_version()})")
    if args.device_ms is not None:
        slowdown = args.device_ms / (result.cpu_s * 1e3)
        low, high = SLOWDOWN_RANGE
        print(f"slowdown = {args.device_ms:g} / {result.cpu_s * 1e3:.4g} = {slowdown:.3g}"
              + ("" if low <= slowdown <= high else f" (outside {low:g}..{high:g}: a device profile cannot use it)"))
    return 0


def cpu_score_command() -> int:
    from nac_onboard.compute import cpu_score
    from nac_onboard.compute.device import load_device_profile, shipped_devices

    score = cpu_score.measure_and_cache()
    print(f"this host: 7-Zip single-thread rating {score:g} MIPS (kept for this CPU)")
    for name in shipped_devices():
        device = load_device_profile(name)
        print(f"{name}: {device.cpu_score_mips:g} MIPS: slowdown {device.slowdown:.3g}")
    return 0


def agent_command(args) -> int:
    from nac_onboard.agent.daemon import run_agent

    config = load_agent_config(args.config)
    if not args.run_id and not config.log.run_id and os.environ.get("NAC_RUN_ID"):
        check_name(os.environ["NAC_RUN_ID"], "$NAC_RUN_ID (the run directory's name)")
    if args.log_dir:
        config = dataclasses.replace(config, log=dataclasses.replace(config.log, dir=args.log_dir))
    try:
        return run_agent(config, args.run_id, ready_line=lambda text: print(text, flush=True))
    except OSError as err:  # a port in use, a log directory we may not write
        raise OperationFailed(f"agent {config.vehicle.id}: {err}") from None


def throughput_command(args) -> int:
    from nac_onboard.link.throughput import ThroughputServer, probe

    if args.action == "server":
        if not 0 <= args.port <= 65535:
            raise BadInput(f"throughput server: --port must be in 0..65535 (0: any free port), not {args.port}")
        try:
            server = ThroughputServer(args.bind, args.port)
        except OSError as err:
            raise OperationFailed(f"cannot listen on {args.bind}:{args.port}: {err.strerror}") from None
        try:  # the line says it is ready, and a SIGTERM may follow it at once
            print(f"throughput server listening on {args.bind}:{server.port}", flush=True)
            server.serve_forever()
        except KeyboardInterrupt:
            pass
        return 0
    duration_s = args.duration_s if args.duration_s is not None or args.nbytes is not None else 1.0
    try:  # a bad answer is a ProbeError (exit 1, its sentence); our own settings out of range are bad input
        result = probe(args.host, args.port, duration_s=duration_s, nbytes=args.nbytes,
                       interval_s=args.interval_s, rate_bps=args.rate_bps)
    except ValueError as err:
        raise BadInput(f"throughput probe: {err}") from None
    print(json.dumps(result, indent=2, allow_nan=False))  # checked values only: NaN or Infinity would be a bug
    return 0


def log_check(files: list[str]) -> int:
    from nac_onboard.flight_log import read_jsonl

    status = 0
    for name in files:
        try:
            read = read_jsonl(name)  # a regular file within the log limit, else BadInput naming it
        except BadInput as err:
            print(f"nac-onboard log check: {err}", file=sys.stderr)
            status = 2
            continue
        kinds: dict[str, int] = {}
        for record in read.records:
            kinds[record["kind"]] = kinds.get(record["kind"], 0) + 1
        summary = ", ".join(f"{k} {n}" for k, n in sorted(kinds.items()))
        print(f"{name}: {len(read.records)} records ({summary})")
        for problem in read.problems:
            print(f"  warning: {problem}")
        if read.problems:
            status = max(status, 1)
    return status


if __name__ == "__main__":
    sys.exit(main())
