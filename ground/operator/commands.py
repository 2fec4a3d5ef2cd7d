"""What each `nac-ground` command does, as importable functions over the MAVLink client.

Functions print what the operator needs to `out` and raise typed errors; the CLI maps them to exit codes.
"""

from __future__ import annotations

import sys
import time

from ground.operator.table import render
from missions import convert_mission, load_mission, save_mission
from missions.firmware import ARDUCOPTER, Firmware
from missions.model import MavCmd, Mission, MissionType
from nac_onboard.mavlink.client import CommandError, LinkError, MavlinkClient, words
from nac_onboard.mavlink.dialect import COPTER_MODES, M, enum_name, mission_catalogue
from nac_onboard.mavlink.mission_transfer import MissionError


class TransferProgress:
    """A transfer progress bar on stderr: redrawn in place on a terminal, one closing line otherwise."""

    def __init__(self, label: str, stream=None, width: int = 30):
        stream = sys.stderr if stream is None else stream  # the stderr of now, not of import time
        self.label, self.stream, self.width = label, stream, width
        self.tty = hasattr(stream, "isatty") and stream.isatty()

    def __call__(self, done: int, total: int) -> None:
        if self.tty or done == total:
            filled = self.width * done // max(total, 1)
            end = "\n" if done == total else ""
            self.stream.write(f"\r{self.label} [{'#' * filled}{'.' * (self.width - filled)}] {done}/{total}{end}")
            self.stream.flush()


def connect(client: MavlinkClient, wait_s: float) -> int:
    """Wait for the target vehicle's heartbeat; returns its sysid."""
    client.wait_heartbeat(wait_s)
    return client.sysid


def arm(client: MavlinkClient, out, arm_motors: bool = True) -> None:
    client.command_ok(MavCmd.COMPONENT_ARM_DISARM, 1 if arm_motors else 0)
    print(f"vehicle {client.sysid}: {'armed' if arm_motors else 'disarmed'}", file=out)


def set_mode(client: MavlinkClient, name: str, out) -> None:
    client.command_ok(MavCmd.DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES[name])
    print(f"vehicle {client.sysid}: mode {name}", file=out)


def takeoff(client: MavlinkClient, alt_m: float, out) -> None:
    # ArduCopter takes off only in GUIDED, as MAVSDK and QGC switch before the command; a refused takeoff puts the
    # vehicle back in the mode it was in, so that a refusal changes nothing.
    before = client.vehicles[client.sysid].mode
    client.command_ok(MavCmd.DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES["GUIDED"])
    try:
        client.command_ok(MavCmd.NAV_TAKEOFF, 0, 0, 0, float("nan"), 0, 0, alt_m)
    except CommandError:
        if before in COPTER_MODES and before != "GUIDED":
            back = client.command(MavCmd.DO_SET_MODE, M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, COPTER_MODES[before])
            if back == M.MAV_RESULT_ACCEPTED:
                print(f"vehicle {client.sysid}: back in {before}", file=out)
        raise
    print(f"vehicle {client.sysid}: taking off to {alt_m:g} m", file=out)


def land(client: MavlinkClient, out) -> None:
    client.command_ok(MavCmd.NAV_LAND)
    print(f"vehicle {client.sysid}: landing", file=out)


def rtl(client: MavlinkClient, out) -> None:
    client.command_ok(MavCmd.NAV_RETURN_TO_LAUNCH)
    print(f"vehicle {client.sysid}: returning to launch", file=out)


def mission_start(client: MavlinkClient, out) -> None:
    client.command_ok(MavCmd.MISSION_START, 0, 0)
    print(f"vehicle {client.sysid}: mission started", file=out)


def _upload_list(client: MavlinkClient, items, mission_type: int, label: str) -> None:
    sent_s = time.monotonic()
    result = client.upload(items, mission_type, progress=TransferProgress(label))
    if result != M.MAV_MISSION_ACCEPTED:
        at = client.last_item_sent
        item = f" at item {at} ({enum_name('MAV_CMD', items[at].command)})" if at is not None else ""
        raise MissionError(f"vehicle {client.sysid} refused the {label}{item}"
                           f"{words(client.said_since(client.sysid, sent_s))}", result)


def mission_upload(client: MavlinkClient, mission: Mission, out) -> None:
    """Upload mission, fence and rally points. An empty fence or rally list is left as it is on the vehicle, and so
    is the mission when the file holds only a fence or rally points (QGC saves such plans); a file of home alone
    clears it."""
    with_mission = bool(mission.items or not (mission.fence or mission.rally))
    if with_mission:
        _upload_list(client, mission.to_wire(), MissionType.MISSION, "mission")
    for items, mission_type, label in ((mission.fence, MissionType.FENCE, "fence"),
                                       (mission.rally, MissionType.RALLY, "rally points")):
        if items:
            _upload_list(client, items, mission_type, label)
    parts = ([f"mission of {len(mission.items)} items"] if with_mission else []) \
        + ([f"fence of {len(mission.fence)} items"] if mission.fence else []) \
        + ([f"{len(mission.rally)} rally points"] if mission.rally else [])
    print(f"vehicle {client.sysid}: {', '.join(parts)} accepted"
          + ("" if with_mission else " (its mission left as it was)"), file=out)


def mission_download(client: MavlinkClient, path: str, out) -> Mission:
    items = client.download(MissionType.MISSION, progress=TransferProgress("mission"))
    fence = client.download(MissionType.FENCE)
    rally = client.download(MissionType.RALLY)
    mission = Mission.from_wire(items)
    mission.fence, mission.rally = fence, rally
    save_mission(mission, path)
    print(f"vehicle {client.sysid}: {len(mission.items)} mission items, {len(fence)} fence items, "
          f"{len(rally)} rally points written to {path}", file=out)
    return mission


def mission_clear(client: MavlinkClient, out) -> None:
    result = client.clear(MissionType.MISSION)
    if result != M.MAV_MISSION_ACCEPTED:
        raise MissionError(f"vehicle {client.sysid} refused to clear its mission", result)
    print(f"vehicle {client.sysid}: mission cleared", file=out)


def load_for_flight(path: str, firmware: Firmware | None = ARDUCOPTER) -> Mission:
    """Read a mission file and check it flies: any command of the MAVLink dialect, and of those only what
    `firmware` takes at upload (None: any); MissionFileError names the file, the item and the problem."""
    return load_mission(path, catalogue=mission_catalogue(), firmware=firmware)


def print_notes(path: str, mission: Mission, out) -> None:
    """What the reader did that the file did not say outright (a survey's stored items, rows renumbered), once."""
    for note in mission.notes:
        print(f"{path}: note: {note}", file=out)


def mission_validate(path: str, out, firmware: Firmware | None = ARDUCOPTER) -> Mission:
    mission = load_for_flight(path, firmware)
    print_notes(path, mission, out)
    print(f"{path}: valid{f' for {firmware.name}' if firmware else ''}, {len(mission.items)} mission items, "
          f"{len(mission.fence)} fence items, {len(mission.rally)} rally points", file=out)
    return mission


def mission_convert(source: str, target: str, out) -> None:
    mission = convert_mission(source, target)
    print_notes(source, mission, out)
    print(f"{source} -> {target}: {len(mission.items)} items", file=out)


def wait_for(client: MavlinkClient, what: str, timeout_s: float, out) -> None:
    """Block until the mission is complete or the vehicle is on the ground; LinkError on timeout."""
    deadline = time.monotonic() + timeout_s
    sysid = client.sysid
    while time.monotonic() < deadline:
        client.poll(min(0.2, max(deadline - time.monotonic(), 0.0)))
        v = client.vehicles.get(sysid)
        if v is None:
            continue
        if what == "landed" and v.landed == "on ground":
            print(f"vehicle {sysid}: on the ground{'' if v.armed else ', disarmed'}", file=out)
            return
        if what == "mission-complete" and v.mission_total and (
                v.mission_state == M.MISSION_STATE_COMPLETE or v.mission_total in v.reached):
            print(f"vehicle {sysid}: mission complete ({v.mission_total} items)", file=out)
            return
        if v.link_age_s() > 5.0:
            raise LinkError(f"vehicle {sysid} silent for {v.link_age_s():.0f} s while waiting for {what}")
    v = client.vehicles.get(sysid)
    state = f"at item {v.mission_seq}/{v.mission_total}, {v.landed}" if v else "never heard"
    raise LinkError(f"vehicle {sysid}: not {what.replace('-', ' ')} after {timeout_s:g} s ({state})")


HEARTBEAT_QUIET_S = 1.2  # heartbeats come at 1 Hz: this long without a new vehicle, every vehicle has spoken


def status(client: MavlinkClient, listen_s: float, out) -> dict:
    """Listen for listen_s, or until every link has a vehicle with a position and no new vehicle has appeared for
    a heartbeat's interval (one link, a telemetry radio, may carry several vehicles); then print the table."""
    deadline = time.monotonic() + listen_s
    known, last_new = 0, time.monotonic()
    while time.monotonic() < deadline:
        client.poll(min(0.2, max(deadline - time.monotonic(), 0.0)))
        vs = client.vehicles.values()
        if len(vs) != known:
            known, last_new = len(vs), time.monotonic()
        if (len({v.link for v in vs}) >= len(client.links) and all(v.lat_deg == v.lat_deg for v in vs)
                and time.monotonic() - last_new >= HEARTBEAT_QUIET_S):
            break
    where = ", ".join(link.uri for link in client.links)
    if not client.vehicles:
        raise LinkError(f"no vehicle heard on {where} within {listen_s:g} s")
    shown = client.vehicles
    if client.sysid is not None:  # --sysid: that vehicle alone, or a failure naming the ones heard
        if client.sysid not in client.vehicles:
            heard = ", ".join(str(k) for k in sorted(client.vehicles))
            raise LinkError(f"vehicle {client.sysid} not heard on {where} within {listen_s:g} s (heard: {heard})")
        shown = {client.sysid: client.vehicles[client.sysid]}
    print(render(shown, time.monotonic()), file=out)
    return shown


def monitor(client: MavlinkClient, refresh_s: float, duration_s: float | None, out) -> None:
    """Redraw the table every refresh_s until duration_s passes (or Ctrl-C)."""
    clear = "\x1b[H\x1b[2J" if hasattr(out, "isatty") and out.isatty() else ""
    end = None if duration_s is None else time.monotonic() + duration_s
    next_draw = time.monotonic() + refresh_s
    while end is None or time.monotonic() < end:
        client.poll(max(0.0, min(next_draw - time.monotonic(), 0.2)))
        if time.monotonic() >= next_draw:
            next_draw += refresh_s
            stamp = time.strftime("%H:%M:%S")
            print(f"{clear}nac-ground monitor  {stamp}  ({len(client.vehicles)} vehicles)", file=out)
            print(render(client.vehicles, time.monotonic()), file=out, end="\n\n" if not clear else "\n", flush=True)
