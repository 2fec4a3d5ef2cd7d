"""`nac-sitl`: run the multi-vehicle MAVLink simulator.

    nac-sitl run --vehicles 4 --speedup 5
"""

from __future__ import annotations

import argparse
import logging
import re
import signal
import sys
import threading
from pathlib import Path

from missions.geo import Home
from nac_onboard.address import parse_host_port
from nac_onboard.errors import BadInput, run_cli
from nac_onboard.inputs import MAX_CONFIG_BYTES, check_name, number_arg, parse_number, read_bounded_text
from nac_onboard.mavlink.signing import load_signing_key, state_path
from nac_onboard.records import kinds
from sitl.server import Sitl, SitlConfig, SitlError
from sitl.vehicle.params import parse_param_file

log = logging.getLogger(__name__)


MAX_VEHICLES = 250


def _home(text: str) -> Home:
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"expected LAT,LON,ALT_M (e.g. 47.39,8.54,488), got {text[:60]!r}")
    try:
        lat, lon, alt = (parse_number(p, name, low, high, unit=unit) for p, name, low, high, unit in zip(
            parts, ("latitude", "longitude", "altitude"), (-90, -180, -500), (90, 180, 10_000),
            ("degrees", "degrees", "m"), strict=True))
    except BadInput as err:
        raise argparse.ArgumentTypeError(f"LAT,LON,ALT_M {text[:60]!r}: {err}") from None
    return Home(lat, lon, alt)


def _host_port(text: str) -> tuple[str, int]:
    try:
        return parse_host_port(text, "--out")
    except BadInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nac-sitl", description="NAC multi-vehicle MAVLink SITL")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="serve N simulated vehicles until interrupted")
    run.add_argument("--vehicles", type=number_arg(1, MAX_VEHICLES, integer=True), default=1,
                     help="number of vehicles (sysid 1..N)")
    run.add_argument("--speedup", type=number_arg(0.1, 1000), default=1.0,
                     help="simulated seconds per wall-clock second")
    run.add_argument("--home", type=_home, default=Home(47.397742, 8.545594, 488.0), metavar="LAT,LON,ALT_M",
                     help="the first vehicle's home (default: 47.397742,8.545594,488, PX4's Zurich field; "
                          "south and west negative, e.g. --home -35.363261,149.165230,584)")
    run.add_argument("--spacing-m", type=number_arg(0, 10_000, unit="m"), default=5.0,
                     help="vehicle i starts i*D metres east of home")
    run.add_argument("--seed", type=number_arg(0, 2**32 - 1, integer=True), default=0,
                     help="seed for GPS noise and injected packet loss")
    run.add_argument("--params", type=Path, help="parameter file (NAME VALUE per line) applied to every vehicle")
    run.add_argument("--host", default="127.0.0.1", help="where the UDP links are sent")
    run.add_argument("--gcs-base-port", type=_port, default=14550, help="ground link of vehicle i: base + step*i")
    run.add_argument("--companion-base-port", type=_port, default=14551, help="companion link: base + step*i")
    run.add_argument("--tcp-base-port", type=number_arg(0, 65535, integer=True), default=5760,
                     help="TCP server: base + step*i (0 = off)")
    run.add_argument("--tcp-bind", default="127.0.0.1",
                     help="address the TCP servers listen on (another address exposes the vehicles to that network)")
    run.add_argument("--port-step", type=number_arg(1, 1000, integer=True), default=10,
                     help="port increment between vehicles")
    run.add_argument("--out", type=_host_port, action="append", default=[],
                     help="extra ground link HOST:PORT (port + step*i per vehicle); repeatable")
    run.add_argument("--signing-key-file", type=Path,
                     help="MAVLink 2 signing: 64 hex characters or a passphrase; unsigned input is refused")
    run.add_argument("--telemetry-radio", default="", metavar="RADIO",
                     help="lose ground-link frames with distance as a telemetry radio does (sik-915); "
                          "default: a lossless link")
    run.add_argument("--ground-station", type=_home, metavar="LAT,LON,ALT_M",
                     help="where the telemetry radio's ground antenna is (default: at each vehicle's home)")
    run.add_argument("-v", "--verbose", action="store_true")
    exp = sub.add_parser("experiment", help="run a scenario end to end: SITL, agents, missions, MPI job, report")
    exp.add_argument("scenario", help="scenario TOML, or the name of a shipped one (sitl/scenarios/)")
    exp.add_argument("--speedup", type=number_arg(0.1, 1000),
                     help="simulated seconds per wall-clock second (default: the "
                                                   "scenario's, real time unless it says otherwise)")
    exp.add_argument("--out", type=Path, help="run directory (default runs/SCENARIO-YYYYmmddTHHMMSS)")
    exp.add_argument("--base-port", type=number_arg(1024, 65535, integer=True), default=14550,
                     help="first UDP port; each vehicle uses 10")
    exp.add_argument("--no-analysis", action="store_true", help="leave the run directory unanalysed")
    exp.add_argument("--network", choices=["kernel", "sleep"],
                     help="kernel: each companion in its own network namespace, links shaped by tc/nftables from "
                          "the live positions (needs root); sleep: transfers sleep bits / capacity, the research's "
                          "method (default: kernel where it can run)")
    exp.add_argument("--links", default="model",
                     help="model: links from the radio model and the live positions; replay:RUN_DIR: each pair's "
                          "throughput as a recorded run measured it, interpolated over simulated time")
    exp.add_argument("--view", nargs="?", const="127.0.0.1:8765", metavar="ADDR:PORT",
                     help="serve the live page while the run goes on (default 127.0.0.1:8765; another address "
                          f"only when given) and save its screenshot as RUN_DIR/{kinds.VIEW_PNG.path}")
    exp.add_argument("-v", "--verbose", action="store_true")
    radio = sub.add_parser("radio", help="a channel's throughput against distance: median, 95 %% band, MCS, range")
    radio.add_argument("channel", help="preset (paper-sim, wifi-flight, wifi-open-field) or channel TOML")
    radio.add_argument("--distances-m", default="1,2,5,8,10,12,15,18,20,22,25,28,30",
                       help="comma-separated distances (m)")
    radio.add_argument("--draws", type=number_arg(10, 100_000, integer=True), default=2000,
                       help="independent links drawn per distance")
    radio.add_argument("-v", "--verbose", action="store_true")
    return parser


def radio_table(channel: str, distances_text: str, draws: int, out=None) -> None:
    out = out or sys.stdout  # looked up per call: a caller may have replaced sys.stdout since import
    from nac_onboard.radio.air_link import rate_band
    from nac_onboard.radio.files import load_channel

    distances = [parse_number(x, "--distances-m (comma-separated metres)", 0, 1e6, low_open=True, unit="m")
                 for x in distances_text.split(",")[:1000]]
    if not distances or min(distances) <= 0 or not 10 <= draws <= 100_000:
        raise BadInput("--distances-m must be positive and --draws 10..100000")
    model = load_channel(channel)
    band = rate_band(model, distances, draws)
    print(model.describe(), file=out)
    print(f"median range {model.range_m():.1f} m; sources: {model.sources or 'not given'}", file=out)
    print(f"{'distance_m':>10} {'mcs':>4} {'median_mbps':>12} {'p2.5_mbps':>10} {'p97.5_mbps':>11} {'in_range':>9}",
          file=out)
    for k, d in enumerate(band["distance_m"]):
        mcs = "-" if band["mcs"][k] < 0 else str(band["mcs"][k])
        print(f"{d:>10g} {mcs:>4} {band['median_bps'][k] / 1e6:>12.2f} {band['low_bps'][k] / 1e6:>10.2f} "
              f"{band['high_bps'][k] / 1e6:>11.2f} {band['in_range_fraction'][k]:>9.0%}", file=out)


def _port(text: str) -> int:
    return number_arg(1, 65535, integer=True)(text)


def config_from_args(args: argparse.Namespace) -> SitlConfig:
    if not 1 <= args.vehicles <= MAX_VEHICLES:
        raise BadInput(f"--vehicles must be 1..{MAX_VEHICLES}, got {args.vehicles}")
    if not 0.1 <= args.speedup <= 1000:
        raise BadInput(f"--speedup must be 0.1..1000, got {args.speedup}")
    for option, base in [("--gcs-base-port", args.gcs_base_port), ("--companion-base-port",
                         args.companion_base_port), ("--tcp-base-port", args.tcp_base_port or 1),
                         *(("--out", port) for _, port in args.out)]:
        if base + args.port_step * (args.vehicles - 1) > 65535:
            raise BadInput(f"{option} {base}: {args.vehicles} vehicles {args.port_step} ports apart need ports up to "
                           f"{base + args.port_step * (args.vehicles - 1)}, beyond 65535")
    params = {}
    if args.params is not None:
        text = read_bounded_text(args.params, "parameter file", MAX_CONFIG_BYTES)
        params = parse_param_file(text, str(args.params))
    signing_key = signing_state = None
    if args.signing_key_file is not None:
        signing_key = load_signing_key(args.signing_key_file)
        signing_state = str(state_path(args.signing_key_file))
    return SitlConfig(
        vehicles=args.vehicles, speedup=args.speedup, home=args.home, spacing_m=args.spacing_m, seed=args.seed,
        params=params, host=args.host, gcs_base_port=args.gcs_base_port,
        companion_base_port=args.companion_base_port, tcp_base_port=args.tcp_base_port, tcp_bind=args.tcp_bind,
        port_step=args.port_step, extra_outs=tuple(args.out), signing_key=signing_key,
        signing_state_file=signing_state, telemetry_radio=args.telemetry_radio, ground_station=args.ground_station,
    )


def run(config: SitlConfig, stop: threading.Event | None = None, out=None) -> None:
    """Serve until `stop` is set (or SIGINT/SIGTERM when run from the command line)."""
    out = out or sys.stdout
    sim = Sitl(config)
    if stop is None:  # before "ready": a SIGTERM right after it is the operator's stop, not run_cli's Terminated
        stop = threading.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())
    for i, ends in enumerate(sim.endpoints):
        home = sim.homes[i]
        listed = ", ".join(f"{name} {where}" for name, where in ends.items())
        print(f"vehicle {i + 1} sysid {i + 1} home {home.lat_deg:.7f},{home.lon_deg:.7f},{home.alt_m:.1f}: "
              f"{listed}", file=out)
    print(f"nac-sitl ready: {config.vehicles} vehicles, speedup {config.speedup:g}x "
          f"(clients listen: udpin:0.0.0.0:{config.gcs_base_port})", file=out, flush=True)
    sim.start()
    try:
        _wait(sim, stop)
    finally:
        sim.stop()
        st = sim.stats
        print(f"nac-sitl stopped at t={sim.t_s:.1f} s simulated: {st['steps']} steps, {st['overruns']} times behind "
              f"the wall clock, {st['bad_frames']} bad frames, {st['handler_errors']} handler errors, "
              f"{st['io_errors']} socket errors", file=out, flush=True)


def _wait(sim: Sitl, stop: threading.Event) -> None:
    while not stop.wait(0.5):
        if not sim.alive:
            raise SitlError("the simulation loop stopped on an internal error (see the log above)")


def experiment(args: argparse.Namespace, out=None) -> int:
    out = out or sys.stdout
    from sitl.experiment.runner import run_scenario
    from sitl.experiment.scenario import load_scenario

    if args.out is not None:  # its last part names the run in every agent's log root (log.run_id)
        check_name(args.out.resolve().name, f"--out {args.out}: the run directory's own name")
    scenario = load_scenario(args.scenario)
    speedup = args.speedup if args.speedup is not None else scenario.default_speedup
    from sitl.experiment.commands import PORTS_PER_VEHICLE

    top = args.base_port + PORTS_PER_VEHICLE * len(scenario.vehicles) - 1
    if top > 65535:
        raise BadInput(f"--base-port {args.base_port}: {len(scenario.vehicles)} vehicles need {PORTS_PER_VEHICLE} "
                       f"ports each, up to {top}, beyond 65535")
    if not 0 < speedup <= scenario.max_speedup:
        # the notes say why at length (paragraphs of measurements): named, not quoted
        why = scenario.device_limit or (f"its max_speedup, why in its notes ({scenario.path})" if scenario.notes
                                        else "its max_speedup")
        raise BadInput(f"{scenario.name}: --speedup {speedup:g} is outside what this scenario allows "
                       f"(up to {scenario.max_speedup:.3g}x: {why})")
    # SIGTERM is Ctrl-C (run_cli): the run stops, its partial report is written, and it exits 143
    result = run_scenario(scenario, args.out, speedup, args.base_port, out, analyze=not args.no_analysis,
                          network=args.network, links=args.links, view=args.view)
    return result.outcome.exit_code


COORDINATE_OPTIONS = ("--home", "--ground-station")


def joined_coordinates(argv: list[str]) -> list[str]:
    """`--home -35.36,149.16,584` as `--home=-35.36,...`: argparse takes a value starting with '-' that is not a
    plain number for an option and refuses it; a southern or western home is a coordinate, not an option."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in COORDINATE_OPTIONS and re.match(r"-[\d.]", arg):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(joined_coordinates(sys.argv[1:] if argv is None else argv))
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.command == "experiment":
        return run_cli("nac-sitl", lambda: experiment(args))
    if args.command == "radio":
        return run_cli("nac-sitl", lambda: radio_table(args.channel, args.distances_m, args.draws) or 0)
    return run_cli("nac-sitl", lambda: run(config_from_args(args)) or 0)


if __name__ == "__main__":
    sys.exit(main())
