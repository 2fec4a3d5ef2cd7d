"""`nac-ground`: the operator's command line over the MAVLink client.

    nac-ground [--connect URI ...] [--sysid N] [--signing-key-file F] COMMAND ...
    nac-ground view RUN_DIR [--follow] [--address HOST:PORT] [--screenshot FILE]   a run in a browser
    nac-ground view --live --connect URI [--connect URI ...] [--feed HOST:PORT]     vehicles live over MAVLink

Exit codes: 0 ok, 1 the vehicle refused or did not answer in time, 2 bad input (nothing was sent).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from missions.firmware import FIRMWARES
from nac_onboard.errors import BadInput, run_cli
from nac_onboard.inputs import id_arg, number_arg
from nac_onboard.records import kinds


def build_parser() -> argparse.ArgumentParser:
    from nac_onboard.mavlink.client import DEFAULT_URI
    from nac_onboard.mavlink.dialect import COPTER_MODES

    parser = argparse.ArgumentParser(prog="nac-ground", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--connect", action="append", metavar="URI",
                        help=f"link to listen on or dial (repeatable; default {DEFAULT_URI} or $NAC_MAVLINK_URI): "
                             "udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, serial:DEVICE:BAUD")
    parser.add_argument("--sysid", type=number_arg(1, 255, integer=True),
                        help="vehicle to command (default: the first one heard)")
    parser.add_argument("--signing-key-file", type=Path, help="MAVLink 2 signing key (64 hex chars or passphrase)")
    parser.add_argument("--wait-s", type=number_arg(0, 3600, low_open=True, unit="s"), default=5.0,
                        help="how long to wait for the vehicle's heartbeat")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    mission = sub.add_parser("mission", help="upload, download, clear, validate, convert, start")
    msub = mission.add_subparsers(dest="action", required=True, metavar="ACTION")
    upload = msub.add_parser("upload", help="upload a .plan or QGC WPL file")
    upload.add_argument("file")
    msub.add_parser("download", help="save the vehicle's mission (.plan or .waypoints by extension)") \
        .add_argument("file")
    msub.add_parser("clear", help="delete the vehicle's mission")
    validate = msub.add_parser("validate", help="check a mission file offline")
    validate.add_argument("file")
    for checked in (upload, validate):
        checked.add_argument("--firmware", choices=[*FIRMWARES, "any"], default="arducopter",
                             help="also refuse, naming the item, what this firmware refuses at upload (default "
                                  "arducopter, as NAC's SITL; any: only what MAVLink itself forbids)")
    convert = msub.add_parser("convert", help="convert between .plan and QGC WPL 110")
    convert.add_argument("source")
    convert.add_argument("target")
    msub.add_parser("start", help="start the uploaded mission (MISSION_START)")

    sub.add_parser("arm", help="arm the motors")
    sub.add_parser("disarm", help="disarm the motors")
    sub.add_parser("takeoff", help="GUIDED takeoff to ALT_M above home").add_argument("alt_m", type=number_arg(
        0, 10_000, low_open=True, unit="m"))
    sub.add_parser("mode", help=f"set a flight mode ({', '.join(sorted(COPTER_MODES))})").add_argument("name")
    sub.add_parser("land", help="land where the vehicle is")
    sub.add_parser("rtl", help="return to launch")
    wait = sub.add_parser("wait", help="block until the mission is complete or the vehicle has landed")
    wait.add_argument("what", choices=["mission-complete", "landed"])
    wait.add_argument("--timeout-s", type=number_arg(0, 86400, low_open=True, unit="s"), default=600.0)
    status = sub.add_parser("status", help="one table of every vehicle heard")
    status.add_argument("--listen-s", type=number_arg(0, 3600, low_open=True, unit="s"), default=3.0)
    monitor = sub.add_parser("monitor", help="live table of every vehicle heard (Ctrl-C to stop)")
    monitor.add_argument("--refresh-s", type=number_arg(0.05, 3600, unit="s"), default=1.0)
    monitor.add_argument("--duration-s", type=number_arg(0, 7 * 86400, low_open=True, unit="s"),
                         help="stop after this long (default: until Ctrl-C)")
    _add_logs_parser(sub)
    _add_view_parser(sub)
    return parser


def view_parser() -> argparse.ArgumentParser:
    """`nac-ground view ...` alone: parsing it imports no MAVLink stack (pymavlink is a quarter of a second of a
    replay's start, and only --live uses it)."""
    parser = argparse.ArgumentParser(prog="nac-ground", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_view_parser(parser.add_subparsers(dest="command", required=True, metavar="COMMAND"))
    return parser


def _add_view_parser(sub) -> None:
    view = sub.add_parser("view", help="a run in a browser, replayed or live; or vehicles live over MAVLink")
    view.add_argument("run_dir", type=Path, nargs="?", help="run directory (optional with --live)")
    view.add_argument("--address", default="127.0.0.1:8765", help="HOST:PORT to serve on (default %(default)s; "
                                                                   "loopback unless another address is given)")
    view.add_argument("--follow", action="store_true",
                      help="live: follow the run directory as its logs are written (an experiment, a flight)")
    view.add_argument("--live", action="store_true", help="watch vehicles live over MAVLink (--connect) and the "
                                                          "master agent's state feed (--feed)")
    view.add_argument("--connect", action="append", dest="view_connect", metavar="URI", default=[],
                      help="with --live: a MAVLink link to watch (repeatable): udpin:HOST:PORT, tcp:..., serial:...")
    view.add_argument("--feed", metavar="HOST:PORT", help="with --live: the master agent's state feed (ids, roles, "
                                                          "positions of every peer)")
    view.add_argument("--screenshot", type=Path, metavar="FILE",
                      help="save a PNG of the page at the end of the run (headless Chromium) and exit; with --live, "
                           "once the first vehicle is drawn (at most 10 s)")
    view.add_argument("--allow-host", action="append", dest="allowed_hosts", metavar="NAME", default=[],
                      help="a name browsers may use for this server beside its address (and localhost on a "
                           "loopback bind); any other Host header is refused (421), against DNS rebinding")


def _add_logs_parser(sub) -> None:
    logs = sub.add_parser("logs", help="analyse run directories: tables, figures, report; calibrate a channel")
    lsub = logs.add_subparsers(dest="action", required=True, metavar="ACTION")
    analyze = lsub.add_parser("analyze", help="tables (CSV), figures (PNG) and report.md of one run")
    analyze.add_argument("run_dir", type=Path)
    analyze.add_argument("--out", type=Path, help="where to write tables, figures and report.md (default: tables "
                                                  "and figures in RUN_DIR/analysis, the report as RUN_DIR/report.md)")
    analyze.add_argument("--no-figures", action="store_true", help="the tables and report.md only (faster)")
    compare = lsub.add_parser("compare", help="two runs side by side (e.g. static vs moving)")
    compare.add_argument("run_a", type=Path)
    compare.add_argument("run_b", type=Path)
    compare.add_argument("--out", type=Path, required=True, help="where to write the comparison")
    for p in (analyze, compare):
        p.add_argument("--master", type=id_arg,
                       help="the master's vehicle id (default: the vehicle whose agent says master)")
        p.add_argument("--bin-m", type=number_arg(0.01, 10_000, unit="m"), default=2.0,
                       help="distance bin width for throughput vs distance")
        p.add_argument("--threshold-mbps", type=number_arg(0, 1e6, unit="Mbit/s"), default=1.0,
                       help="throughput counted as 'in range' for the summary's range figure")
    calibrate = lsub.add_parser("calibrate", help="fit path loss and shadowing to measured throughput: a preset")
    calibrate.add_argument("run_dir", type=Path)
    calibrate.add_argument("--out", type=Path, help="TOML to write (default RUN_DIR/calibrated-RUN.toml)")
    calibrate.add_argument("--base", default="wifi-flight",
                           help="preset or TOML giving the radio (bandwidth, noise, power, rate limits)")
    calibrate.add_argument("--name", help="the preset's name (default calibrated-RUN)")
    calibrate.add_argument("--samples-per-probe", type=number_arg(1, 10_000, integer=True), default=10,
                           help="independent fades one probe averages (about 10 for a 1 s probe while moving)")


def run_logs(args: argparse.Namespace, out=None) -> int:
    out = out or sys.stdout  # looked up per call: a caller may have replaced sys.stdout since import
    from ground.logs import report  # pandas and matplotlib only for the commands that use them

    if args.action == "analyze":
        # without --out, the report is the run's own (RUN/report.md, where the experiment runner writes it): a
        # re-analysis replaces it instead of leaving a second one in analysis/
        report_path = args.out / kinds.REPORT.name if args.out else args.run_dir / kinds.REPORT.name
        tables = report.analyze_run(args.run_dir, args.out, args.master, args.bin_m, args.threshold_mbps,
                                    report_path=report_path, draw_figures=not args.no_figures)
        print(f"{report_path}: {_brief(tables.summary)}", file=out)
        for line in tables.missing:
            print(f"  missing: {line}", file=out)
    elif args.action == "compare":
        comparison = report.compare_runs(args.run_a, args.run_b, args.out, args.master, args.bin_m,
                                         args.threshold_mbps)
        print(f"{comparison.report_path}", file=out)
        for tables in comparison.tables:
            print(f"  {tables.name}: {_brief(tables.summary)}", file=out)
    else:
        model, fit, path = report.calibrate_run(args.run_dir, args.out, args.base, args.name,
                                                args.samples_per_probe)
        low, high = fit["exponent_ci"]
        print(f"{path}: from {fit['probes']} probes at {fit['distance_min_m']:.1f}-{fit['distance_max_m']:.1f} m "
              f"({fit['censored_low']} at nothing, {fit['censored_high']} at the top rate: censored)", file=out)
        print(f"  path-loss exponent n  {fit['exponent']:.2f}  (95 % {low:.2f}-{high:.2f})", file=out)
        low, high = fit["ref_loss_ci_db"]
        print(f"  PL(d0)                {fit['ref_loss_db']:.1f} dB  (95 % {low:.1f}-{high:.1f})", file=out)
        low, high = fit["sigma_ci_db"]
        print(f"  shadowing sigma       {fit['sigma_db']:.2f} dB  (95 % {low:.2f}-{high:.2f})", file=out)
        print(f"  residuals             rms {fit['rms_residual_db']:.2f} dB over {fit['measured']} measured probes",
              file=out)
        print(f"  median range {model.range_m():.1f} m; figure {fit['figure']}; {fit['note']}", file=out)
    return 0


def _brief(summary: dict) -> str:
    parts = [f"{summary.get('vehicles', 0)} vehicles"]
    if "iterations" in summary:
        parts.append(f"{summary['iterations']} iterations, mean {summary['mean_iteration_s']:.3f} s")
    if "probes" in summary:
        parts.append(f"{summary['probes']} probes, mean {summary['mean_throughput_mbps']:.2f} Mbit/s")
    return ", ".join(parts)


def run(args: argparse.Namespace, out=None) -> int:
    out = out or sys.stdout
    if args.command == "logs":
        return run_logs(args, out)
    if args.command == "view":
        from ground.view.serve import replay

        if args.live:
            from ground.view.serve import watch

            return watch(args.view_connect, args.feed, args.run_dir, args.address, out,
                         allowed_hosts=tuple(args.allowed_hosts), screenshot_path=args.screenshot)
        if args.run_dir is None:
            raise BadInput("view: give a RUN_DIR, or --live with --connect URI and/or --feed HOST:PORT")
        return replay(args.run_dir, args.address, args.screenshot, out, live=args.follow,
                      allowed_hosts=tuple(args.allowed_hosts))
    return _run_vehicle_command(args, out)


def _run_vehicle_command(args: argparse.Namespace, out) -> int:
    from ground.operator import commands as ops
    from nac_onboard.mavlink.client import MavlinkClient
    from nac_onboard.mavlink.dialect import COPTER_MODES
    from nac_onboard.mavlink.signing import load_signing_key, state_path

    key = (args.command, getattr(args, "action", None))
    if key == ("mission", "validate"):
        ops.mission_validate(args.file, out, FIRMWARES.get(args.firmware))
        return 0
    if key == ("mission", "convert"):
        ops.mission_convert(args.source, args.target, out)
        return 0
    # Everything that can be refused offline is checked before any link opens: bad input sends nothing.
    mission = ops.load_for_flight(args.file, FIRMWARES.get(args.firmware)) if key == ("mission", "upload") else None
    if mission is not None:
        ops.print_notes(args.file, mission, out)
    if args.command == "mode" and args.name.upper() not in COPTER_MODES:
        raise BadInput(f"unknown mode {args.name!r}; known: {', '.join(sorted(COPTER_MODES))}")
    signing_key = load_signing_key(args.signing_key_file) if args.signing_key_file else None
    signing_state = str(state_path(args.signing_key_file)) if args.signing_key_file else None

    with MavlinkClient(args.connect, sysid=args.sysid, signing_key=signing_key,
                       signing_state_file=signing_state) as client:
        if args.command == "status":
            ops.status(client, args.listen_s, out)
            return 0
        if args.command == "monitor":
            try:
                ops.monitor(client, args.refresh_s, args.duration_s, out)
            except KeyboardInterrupt:
                pass
            return 0
        ops.connect(client, args.wait_s)
        if args.command == "mission":
            {"upload": lambda: ops.mission_upload(client, mission, out),
             "download": lambda: ops.mission_download(client, args.file, out),
             "clear": lambda: ops.mission_clear(client, out),
             "start": lambda: ops.mission_start(client, out)}[args.action]()
        elif args.command in ("arm", "disarm"):
            ops.arm(client, out, args.command == "arm")
        elif args.command == "takeoff":
            ops.takeoff(client, args.alt_m, out)
        elif args.command == "mode":
            ops.set_mode(client, args.name.upper(), out)
        elif args.command == "land":
            ops.land(client, out)
        elif args.command == "rtl":
            ops.rtl(client, out)
        elif args.command == "wait":
            ops.wait_for(client, args.what, args.timeout_s, out)
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args = (view_parser() if argv[:1] == ["view"] else build_parser()).parse_args(argv)
    return run_cli("nac-ground", lambda: run(args))


if __name__ == "__main__":
    sys.exit(main())
