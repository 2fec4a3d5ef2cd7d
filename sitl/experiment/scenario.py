"""A NAC experiment described as data: `nac-sitl experiment SCENARIO.toml` reads one of these.

    name = "paper-flight-moving"
    duration_s = 130            # simulated seconds from the missions' start
    max_speedup = 4             # fidelity limit: --speedup above it is refused; a device profile may lower it
    [channel]  preset = "wifi-flight"           # or a TOML file (what `nac-ground logs calibrate` writes)
               background_airtime = 0.2         # any other channel field overrides the preset's
    [compute]  task = "linreg"  iterations = 0  timeout_s = 3.0  args = []   # no [compute]: no MPI job
               device = "host"                  # or a device profile file: the companions' CPU (docs/compute.md)
               code_k = 0  code_s = 1           # matmul_mds / linreg_gc / matmul_bpcc: the code (docs/compute.md)
               allocation = "speed"  replan_every = 10   # blocks by each worker's speed, re-planned as links change
    [throughput]  period_s = 2.0  duration_s = 0.5  interval_s = 0.1
    [network]  period_s = 0.1  sharing = true   # the kernel network's shaper and the access point's airtime
               air = "htb"  queue_packets = 1000  # or "medium": the 802.11 medium frame by frame (issue 28)
               congestion_control = "host"        # the companions' TCP: this machine's, "cubic" (a Jetson's) or "reno"
    [energy]  companion = "jetson-tx2"  radio = "wifi-router"  companion_mah = 1300   # the companions' side
    [[vehicle]]  id = "master"  role = "master"  mission = "paper-flight-moving/master.plan"  # companion_mah = 500
                 device = "slow.toml"           # this companion's own device profile (a slow one among the rest)
    [[fault]]  at_s = 60  vehicle = "w1"  kind = "link_down"  duration_s = 5

A scenario whose companions have a device profile slower than this host may not run faster than the profiles
allow (device_speedup_limit): its max_speedup, and default_speedup, are lowered to that limit, below 1x where
the host has too few cores for the ranks (time dilation).

A vehicle's home is its mission's planned home (so the plan and the simulator cannot disagree); a vehicle without
a mission gives `home = [lat, lon, alt_m]` and stays on the ground. Paths are relative to the scenario file.
[channel] is resolved here, once: its preset or file with the table's overrides becomes the scenario's one
radio model (Scenario.channel), which the runner writes to the run directory for every process of the run.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from missions import MissionFileError, load_mission
from missions.geo import Home
from missions.model import Mission
from nac_onboard.compute.device import device_path as resolve_device_path
from nac_onboard.compute.device import load_device_profile
from nac_onboard.compute.options import ComputeOptions
from nac_onboard.compute.tasks import all_tasks
from nac_onboard.errors import BadInput
from nac_onboard.inputs import check_id, check_number
from nac_onboard.mavlink.dialect import mission_catalogue
from nac_onboard.radio.channel import ChannelError, ChannelModel
from nac_onboard.radio.files import load_channel
from nac_onboard.radio.medium import DEFAULT_QUEUE_PACKETS
from nac_onboard.tomlfile import get_value, ranged, read_toml, to_dataclass
from sitl.experiment.faults import Fault, FaultKind
from sitl.vehicle import energy
from sitl.vehicle.params import PARAMS_BY_NAME

SCENARIO_DIR = Path(__file__).resolve().parent.parent / "scenarios"
MAX_VEHICLES = 250  # the simulator's limit (nac-sitl run --vehicles), and 10 ports each must fit below 65536
MAX_DURATION_S = 7 * 86400.0  # simulated seconds: a week, far beyond any battery
MAX_SPEEDUP = 1000.0  # as nac-sitl run --speedup
MIN_SPEEDUP = 0.1  # the same
TOP_KEYS = ("name", "description", "duration_s", "max_speedup", "default_speedup", "notes", "params", "channel",
            "compute", "throughput", "network", "energy", "vehicle", "fault")
VEHICLE_KEYS = ("id", "role", "mission", "home", "companion_mah", "device")
FAULT_VALUE_RANGES = {"battery_pct": (0.0, 100.0), "packet_loss_pct": (0.0, 100.0)}


class ScenarioError(BadInput):
    """A scenario file that cannot be run; the message names the file and the key."""


@dataclass(frozen=True)
class VehiclePlan:
    id: str
    role: str
    home: Home
    mission: Mission | None = None
    mission_path: Path | None = None
    companion_mah: float | None = None  # this vehicle's companion pack, if not [energy]'s
    device: str | None = None  # this companion's device profile (an absolute path), if not [compute]'s


@dataclass(frozen=True)
class ComputePlan:
    task: str
    iterations: int = ranged(0, 0, 10_000_000)  # 0: until the scenario ends
    timeout_s: float = ranged(3.0, 0.0, 3600.0, low_open=True, unit="s")
    on_missing: str = "incomplete"
    allocation: str = "equal"
    device: str = "host"  # the companions' CPU: "host" or a device profile file (nac_onboard/compute/device.py)
    code_k: int = ranged(0, 0, 10_000)  # matmul_mds: results that decode (0: the workers less one)
    code_s: int = ranged(1, 0, 10_000)  # linreg_gc: stragglers tolerated
    code_redundancy: float = ranged(1.5, 1.0, 10.0)  # matmul_bpcc: coded units per data block
    batch_units: int = ranged(1, 1, 10_000)  # matmul_bpcc: units per batch sent back
    replan_every: int = ranged(0, 0, 10_000_000)  # iterations between re-plans of the blocks (0: never)
    link_rates: str = "model"  # what the allocation expects of the links: the channel model or the master's probes
    args: tuple[str, ...] = ()


@dataclass(frozen=True)
class ProbePlan:
    period_s: float = ranged(2.0, 0.0, 3600.0, low_open=True, unit="s")
    duration_s: float = ranged(0.5, 0.0, 3600.0, low_open=True, unit="s")
    interval_s: float = ranged(0.1, 0.05, 3600.0, unit="s")  # agents refuse finer intervals
    tool: str = "nac"  # or "iperf3": the real iperf3 between the namespaces (kernel network only)
    concurrent: bool = False  # each worker probed on its own schedule, all at once (one client per link); else in turn


AIRS = ("htb", "medium")
# host: this machine's default, untouched (BBR where this was written); cubic: a Jetson's, Linux's default since
# 2.6.19 (CONFIG_DEFAULT_TCP_CONG), which Ubuntu and NVIDIA's L4T keep: it fills a transmit queue BBR keeps short
CONGESTION_CONTROLS = ("cubic", "reno", "bbr", "host")


@dataclass(frozen=True)
class NetworkPlan:
    period_s: float = 0.1  # simulated seconds between shaper updates
    sharing: bool = True  # the master is the access point: what passes through it shares one airtime budget
    # the kernel network's air: "htb" (a bridge, a rate class per pair, nftables drops) or "medium" (a delay line
    # carrying every frame through the 802.11 medium: queues, channel access, retries; sitl/network/medium_air.py)
    air: str = "htb"
    queue_packets: int = ranged(DEFAULT_QUEUE_PACKETS, 1, 100_000)  # each station's transmit queue ("medium")
    # the companions' TCP congestion control (kernel network): "host" (this machine's default, e.g. BBR) or one named:
    # "cubic", a Jetson's (Linux's default), whose window grows on the wall clock, so a sped-up run's CUBIC is not
    # the 1x run's; "reno", whose window grows per acknowledgement, which the flight scenarios set (docs/radio.md)
    congestion_control: str = "host"


@dataclass(frozen=True)
class EnergyPlan:
    """[energy]: the companions' computer, radio and pack (sitl/vehicle/energy.py); the frames are NAC_FRAME's."""

    companion: str = "jetson-tx2"
    radio: str = "wifi-router"
    companion_cells: int = ranged(4, 1, 14)
    companion_mah: float = ranged(1300.0, 0.0, 100_000.0, low_open=True, unit="mAh")  # assumed: a common 4S size
    dc_dc_efficiency: float = ranged(energy.DC_DC_EFFICIENCY, 0.0, 1.0, low_open=True)
    frame: str = ""  # a frame file ([frame]: energy.Frame's fields) every vehicle flies, instead of NAC_FRAME's


@dataclass(frozen=True)
class Scenario:
    name: str
    path: Path
    description: str
    duration_s: float
    vehicles: tuple[VehiclePlan, ...]
    channel: ChannelModel  # the radio between vehicles: [channel]'s preset or file, the table's overrides applied
    compute: ComputePlan | None
    throughput: ProbePlan | None
    faults: tuple[Fault, ...] = ()
    network: NetworkPlan = NetworkPlan()
    max_speedup: float = 1.0
    default_speedup: float = 1.0
    notes: tuple[str, ...] = field(default_factory=tuple)
    device_limit: str = ""  # why max_speedup is below the file's: the device profiles' limit (device_speedup_limit)
    params: tuple[tuple[str, float], ...] = ()  # autopilot parameters of every vehicle ([params])
    energy: EnergyPlan = EnergyPlan()
    frame: energy.Frame | None = None  # [energy] frame's, loaded

    @property
    def master(self) -> VehiclePlan:
        return next(v for v in self.vehicles if v.role == "master")

    @property
    def workers(self) -> list[VehiclePlan]:
        return [v for v in self.vehicles if v.role == "worker"]

    def companion_mah(self, vehicle: VehiclePlan) -> float:
        """The vehicle's companion pack: its own, or [energy]'s."""
        return vehicle.companion_mah or self.energy.companion_mah


def find_scenario(name_or_path: str) -> Path:
    """A scenario by path, or by name among the shipped ones (sitl/scenarios/NAME.toml)."""
    path = Path(name_or_path)
    if path.exists():
        return path
    shipped = SCENARIO_DIR / f"{name_or_path}.toml"
    if shipped.exists():
        return shipped
    names = ", ".join(sorted(p.stem for p in SCENARIO_DIR.glob("*.toml")))
    raise ScenarioError(f"{name_or_path}: no such scenario file, nor a shipped scenario ({names})")


def load_scenario(name_or_path: str) -> Scenario:
    """The scenario, every key checked (type, finite, range, ids, files) before anything starts: ScenarioError
    (exit 2) names the file, the key and what was expected."""
    path = find_scenario(name_or_path).resolve()
    data = read_toml(path, "scenario", ScenarioError)
    where = str(path)
    unknown = sorted(set(data) - set(TOP_KEYS))
    if unknown:
        raise ScenarioError(f"{where}: unknown key {unknown[0]!r} at the top level (known: {', '.join(TOP_KEYS)})")
    duration_s = check_number(get_value(data, "duration_s", "float", where, ScenarioError), f"{where}: duration_s",
                              0.0, MAX_DURATION_S, low_open=True, unit="simulated s", error=ScenarioError)
    vehicle_tables = _tables(data, "vehicle", where)
    if len(vehicle_tables) > MAX_VEHICLES:
        raise ScenarioError(f"{where}: [[vehicle]]: at most {MAX_VEHICLES} vehicles (10 UDP ports each), "
                            f"got {len(vehicle_tables)}")
    vehicles = tuple(_vehicle(v, path, f"{where}: vehicle {k + 1}") for k, v in enumerate(vehicle_tables))
    roles = [v.role for v in vehicles]
    if roles.count("master") != 1 or len(vehicles) < 2:
        raise ScenarioError(f"{where}: needs one [[vehicle]] with role \"master\" and at least one worker "
                            f"(got roles {roles})")
    ids = [v.id for v in vehicles]
    if len(set(ids)) != len(ids):
        raise ScenarioError(f"{where}: vehicle ids must be unique, got {ids}")
    max_speedup = check_number(data.get("max_speedup", 1.0), f"{where}: max_speedup", MIN_SPEEDUP, MAX_SPEEDUP,
                               unit="x real time", error=ScenarioError)
    default_speedup = check_number(data.get("default_speedup", 1.0), f"{where}: default_speedup", MIN_SPEEDUP,
                                   max_speedup, unit="x real time (0.1 to max_speedup)", error=ScenarioError)
    name = get_value(data, "name", "str", where, ScenarioError, path.stem)
    check_id(name, f"{where}: name (it names the run directory)", ScenarioError)
    scenario = Scenario(
        name=name, path=path,
        description=get_value(data, "description", "str", where, ScenarioError, ""),
        duration_s=duration_s, vehicles=vehicles,
        channel=_channel(_table(data, "channel", where), path, where),
        compute=_compute(_table(data, "compute", where), path, f"{where}: [compute]") if "compute" in data else None,
        throughput=(_probes(_table(data, "throughput", where), f"{where}: [throughput]")
                    if "throughput" in data else None),
        faults=tuple(_fault(f, ids, duration_s, f"{where}: fault {k + 1}")
                     for k, f in enumerate(_tables(data, "fault", where))),
        network=_network(_table(data, "network", where), f"{where}: [network]"),
        max_speedup=max_speedup, default_speedup=default_speedup,
        notes=get_value(data, "notes", "tuple[str, ...]", where, ScenarioError, ()),
        params=_params(_table(data, "params", where), f"{where}: [params]"),
        energy=_energy(_table(data, "energy", where), f"{where}: [energy]", data.get("compute")))
    if scenario.energy.frame:
        scenario = dataclasses.replace(scenario, frame=load_frame(path.parent / scenario.energy.frame))
    if scenario.network.air == "medium":
        _fits_the_frame_level_air(scenario.channel, _table(data, "channel", where), f"{where}: [channel]")
    for k, fault in enumerate(scenario.faults):
        if fault.kind is FaultKind.KILL_WORKER and (scenario.compute is None or fault.vehicle not in
                                            [w.id for w in scenario.workers]):
            raise ScenarioError(f"{where}: fault {k + 1}: kill_worker needs a worker of the MPI job ([compute]), "
                                f"got {fault.vehicle!r}")
        if fault.kind in (FaultKind.LOSE_COMPANION, FaultKind.REBOOT_COMPANION) and scenario.compute is not None \
                and fault.vehicle == scenario.master.id:
            raise ScenarioError(f"{where}: fault {k + 1}: {fault.kind.value} of the MPI job's master ends the job; "
                                "a worker is expected (a lost master is restarted with `nac-onboard compute "
                                "--resume`, docs/compute.md)")
        if fault.kind is FaultKind.REBOOT_COMPANION and fault.duration_s <= 0:
            raise ScenarioError(f"{where}: fault {k + 1}: reboot_companion needs duration_s > 0 (how long the "
                                "companion is away)")
    if scenario.compute is not None:  # a code the fleet cannot hold: refused before anything starts
        c = scenario.compute
        options = ComputeOptions(task=c.task, iterations=None, duration_s=None, out="", code_k=c.code_k,
                                 code_s=c.code_s, code_redundancy=c.code_redundancy, batch_units=c.batch_units)
        try:
            all_tasks()[c.task].check_workers(options, len(scenario.workers))
        except ValueError as err:
            raise ScenarioError(f"{where}: [compute] task {c.task} with {len(scenario.workers)} workers: {err}") \
                from None
    return within_the_devices(scenario)


def device_speedup_limit(scenario: Scenario, host_cores: int | None = None) -> tuple[float, str] | None:
    """The fastest speed-up at which each companion's CPU time is still its device's: (speed-up, why), or None
    when no rank's profile stretches its work (every one "host": then max_speedup is the scenario's own).

    A rank holds each segment of its work until slowdown x its CPU seconds on this host have passed on the run's
    clock (nac_onboard.compute.device.CpuStretch), so at a speed-up s it is on time while its work takes at most
    slowdown / s of wall time per CPU second. The workers compute at once: with more of them than this host's cores
    each gets cores / workers of a core, so s <= slowdown x cores / workers; the master computes alone. The slowdown
    is the profile's (measured, or this host's measured CPU score over the device's)."""
    if scenario.compute is None:
        return None
    cores = host_cores or len(os.sched_getaffinity(0))
    workers = len(scenario.workers)
    limits = []
    for vehicle in (scenario.master, *scenario.workers):
        device = vehicle.device or scenario.compute.device
        if device == "host":
            continue
        profile = load_device_profile(device)
        at_once = workers if vehicle.role == "worker" else 1
        limit = _down_to_two_digits(profile.slowdown * min(1.0, cores / at_once))
        shared = f" and {at_once} workers share this host's {cores} cores" if at_once > cores else ""
        limits.append((limit, f"{vehicle.id}'s companion ({profile.name}) computes {profile.slowdown:.3g} times "
                              f"slower than this host{shared}, so above {limit:.3g}x its work would take longer "
                              f"than the device's"))
    return min(limits, key=lambda limit: limit[0]) if limits else None


def _down_to_two_digits(speedup: float) -> float:
    """A speed-up limit as a user would write it (0.9598 -> 0.95, 2.219 -> 2.2), never above the limit itself."""
    step = 10.0 ** (math.floor(math.log10(speedup)) - 1)
    return round(math.floor(speedup / step + 1e-9) * step, 12)


def within_the_devices(scenario: Scenario) -> Scenario:
    """The scenario with max_speedup and default_speedup at most device_speedup_limit's."""
    limit = device_speedup_limit(scenario)
    if limit is None or limit[0] >= scenario.max_speedup:
        return scenario
    speedup, why = limit
    if speedup < MIN_SPEEDUP:
        raise ScenarioError(f"{scenario.path}: this host cannot run it: {why}, and the simulator runs at "
                            f"{MIN_SPEEDUP:g}x or faster (fewer workers, a faster profile or more cores)")
    return dataclasses.replace(scenario, max_speedup=speedup, default_speedup=min(scenario.default_speedup, speedup),
                               device_limit=why)


def _table(data: dict, key: str, where: str) -> dict:
    value = data.get(key, {})
    if not isinstance(value, dict):
        raise ScenarioError(f"{where}: {key}: expected a table [{key}], got {value!r:.60}")
    return value


def _tables(data: dict, key: str, where: str) -> list[dict]:
    value = data.get(key, [])
    if not isinstance(value, list) or not all(isinstance(t, dict) for t in value):
        raise ScenarioError(f"{where}: {key}: expected tables [[{key}]], got {value!r:.60}")
    return value


def _params(table: dict, where: str) -> tuple[tuple[str, float], ...]:
    """[params]: NAME = number for every simulated autopilot, each a known parameter within its range."""
    if not isinstance(table, dict):
        raise ScenarioError(f"{where}: expected a table of NAME = number")
    out = []
    for name, value in table.items():
        definition = PARAMS_BY_NAME.get(name)
        if definition is None:
            raise ScenarioError(f"{where}: {name}: no such parameter (nac-sitl's are listed in sitl/vehicle/params.py)")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                definition.min <= value <= definition.max):
            raise ScenarioError(f"{where}: {name} = {value!r}: expected a number within "
                                f"{definition.min:g}..{definition.max:g}")
        out.append((name, float(value)))
    return tuple(out)


def _channel(table: dict, scenario_path: Path, where: str) -> ChannelModel:
    """[channel]: `preset` (a name, or a channel TOML relative to the scenario; paper-sim by default), any other
    key a ChannelModel field overriding the preset's, checked as a channel file is."""
    overrides = dict(table)
    source = get_value(overrides, "preset", "str", f"{where}: [channel]", ScenarioError, "paper-sim")
    overrides.pop("preset", None)
    relative = scenario_path.parent / source
    source = str(relative) if relative.suffix == ".toml" else source
    try:
        channel = load_channel(source)
        if overrides:
            channel = to_dataclass(ChannelModel, {**dataclasses.asdict(channel), **overrides},
                                   f"{where}: [channel]", ScenarioError)
    except ChannelError as err:
        raise ScenarioError(f"{where}: [channel] {err}") from None
    return channel


def _vehicle(table: dict, scenario_path: Path, where: str) -> VehiclePlan:
    unknown = sorted(set(table) - set(VEHICLE_KEYS))
    if unknown:
        raise ScenarioError(f"{where}: unknown key vehicle.{unknown[0]} (known: {', '.join(VEHICLE_KEYS)})")
    vehicle_id = get_value(table, "id", "str", where, ScenarioError)
    check_id(vehicle_id, f"{where}: id (a directory and host name)", ScenarioError)
    role = get_value(table, "role", "str", where, ScenarioError)
    if role not in ("master", "worker"):
        raise ScenarioError(f"{where}: role must be \"master\" or \"worker\", got {role!r}")
    if "mission" in table:
        mission_path = scenario_path.parent / get_value(table, "mission", "str", where, ScenarioError)
        try:
            mission = load_mission(mission_path, catalogue=mission_catalogue())
        except MissionFileError as err:
            raise ScenarioError(f"{where} ({vehicle_id}): {err}") from None
        if mission.home is None:
            raise ScenarioError(f"{where} ({vehicle_id}): {mission_path} has no plannedHomePosition")
        home = Home(mission.home.lat_deg, mission.home.lon_deg, mission.home.alt_m)
        return VehiclePlan(vehicle_id, role, home, mission, mission_path, _companion_mah(table, where, vehicle_id),
                           _device(table, scenario_path, where, vehicle_id))
    home = table.get("home")
    if not (isinstance(home, list) and len(home) == 3):
        raise ScenarioError(f"{where} ({vehicle_id}): give mission = \"FILE.plan\" or home = [lat, lon, alt_m]")
    lat, lon, alt = (check_number(x, f"{where} ({vehicle_id}): home[{k}] ({name})", low, high, error=ScenarioError)
                     for k, (x, name, low, high) in enumerate(zip(home, ("latitude", "longitude", "altitude m"),
                                                                  (-90, -180, -500), (90, 180, 10_000), strict=True)))
    return VehiclePlan(vehicle_id, role, Home(lat, lon, alt), companion_mah=_companion_mah(table, where, vehicle_id),
                       device=_device(table, scenario_path, where, vehicle_id))


def _companion_mah(table: dict, where: str, vehicle_id: str) -> float | None:
    if "companion_mah" not in table:
        return None
    return check_number(table["companion_mah"], f"{where} ({vehicle_id}): companion_mah", 0.0, 100_000.0,
                        low_open=True, unit="mAh", error=ScenarioError)


def _device_path(value: str, scenario_path: Path, where: str) -> str:
    """A device profile named in a scenario: a file relative to it or a shipped profile's name (jetson-tx2...),
    checked now (a bad profile: exit 2 naming its field); this host's CPU score is measured once if it needs it."""
    device_path = resolve_device_path(value, scenario_path.parent)
    try:
        load_device_profile(device_path, measure_host=True)
    except BadInput as err:
        raise ScenarioError(f"{where}: device: {err}") from None
    return str(device_path.resolve())


def _device(table: dict, scenario_path: Path, where: str, vehicle_id: str) -> str | None:
    if "device" not in table:
        return None
    return _device_path(get_value(table, "device", "str", where, ScenarioError), scenario_path,
                        f"{where} ({vehicle_id})")


def _compute(table: dict, path: Path, where: str) -> ComputePlan:
    plan = to_dataclass(ComputePlan, table, where, ScenarioError, table="compute")
    if plan.device != "host":
        plan = dataclasses.replace(plan, device=_device_path(plan.device, path, where))
    tasks = all_tasks()
    if plan.task not in tasks:
        raise ScenarioError(f"{where}: compute.task must be one of {', '.join(tasks)}, got {plan.task!r}")
    choices = {"on_missing": ("incomplete", "reassign"), "allocation": ("equal", "capacity", "speed", "energy"),
               "link_rates": ("model", "probes")}
    for key, allowed in choices.items():
        if getattr(plan, key) not in allowed:
            raise ScenarioError(f"{where}: compute.{key} must be one of {', '.join(allowed)}, "
                                f"got {getattr(plan, key)!r}")
    return plan


def _probes(table: dict, where: str) -> ProbePlan:
    plan = to_dataclass(ProbePlan, table, where, ScenarioError, table="throughput")
    if not 0 < plan.duration_s <= plan.period_s:
        raise ScenarioError(f"{where}: [throughput] needs 0 < duration_s <= period_s")
    if plan.tool not in ("nac", "iperf3"):
        raise ScenarioError(f"{where}: tool must be \"nac\" or \"iperf3\", got {plan.tool!r}")
    return plan


def _fits_the_frame_level_air(channel, table: dict, where: str) -> None:
    """The channel fields the frame-level air has no use for, refused: it holds only the run's stations (no other
    networks' airtime) and charges the 802.11 MAC's own costs (no efficiency)."""
    if channel.background_airtime > 0:
        raise ScenarioError(f"{where} background_airtime = {channel.background_airtime:g}: the frame-level air "
                            "([network] air = \"medium\") holds only the run's own stations, so other networks' "
                            "airtime is not modelled there; set it to 0, or use air = \"htb\", which takes it off "
                            "every link's rate")
    if "mac_efficiency" in table or table.get("mac", "802.11") != "802.11":
        key = "mac_efficiency" if "mac_efficiency" in table else "mac"
        raise ScenarioError(f"{where} {key}: the frame-level air ([network] air = \"medium\") charges each frame "
                            "what the 802.11 MAC costs (mac = \"802.11\"), not an efficiency; remove it, or use air "
                            "= \"htb\"")


def _network(table: dict, where: str) -> NetworkPlan:
    plan = to_dataclass(NetworkPlan, table, where, ScenarioError, table="network")
    if plan.air not in AIRS:
        raise ScenarioError(f"{where}: air must be one of {', '.join(AIRS)}, got {plan.air!r}")
    if plan.congestion_control not in CONGESTION_CONTROLS:
        raise ScenarioError(f"{where}: congestion_control must be one of {', '.join(CONGESTION_CONTROLS)}, got "
                            f"{plan.congestion_control!r}")
    if not 0.01 <= plan.period_s <= 10.0:
        raise ScenarioError(f"{where}: period_s must be within 0.01..10 simulated seconds, got {plan.period_s}")
    # a key one air has no use for is refused, not ignored: the run would not be what its file says
    if plan.air == "medium" and not plan.sharing:
        raise ScenarioError(f"{where}: sharing = false: on the frame-level air (air = \"medium\") every station "
                            "shares one medium, frame by frame; sharing is the htb air's choice")
    if plan.air == "htb" and "queue_packets" in table:
        raise ScenarioError(f"{where}: queue_packets: a station's transmit queue is the frame-level air's (air = "
                            "\"medium\"); the htb air has none of its own")
    return plan


def _energy(table: dict, where: str, compute_table) -> EnergyPlan:
    """[energy], its companion by the device profiles' names (a short alias taken); unset, the companion is [compute]'s
    device where that is a shipped Jetson profile: one companion, one name, in both models."""
    table = dict(table)
    if isinstance(table.get("companion"), str):  # any other type is refused by to_dataclass, by name
        table["companion"] = energy.COMPANION_ALIASES.get(table["companion"], table["companion"])
    elif isinstance(compute_table, dict) and compute_table.get("device") in energy.COMPANIONS:
        table["companion"] = compute_table["device"]
    plan = to_dataclass(EnergyPlan, table, where, ScenarioError, table="energy")
    for key, known in (("companion", energy.COMPANIONS), ("radio", energy.RADIOS)):
        if getattr(plan, key) not in known:
            raise ScenarioError(f"{where}: {key} must be one of {', '.join(known)}, got {getattr(plan, key)!r}")
    return plan


def load_frame(path: Path) -> energy.Frame:
    """A frame file's [frame] table (energy.Frame's fields, each with its physical range): ScenarioError naming
    the file, the field and the range."""
    data = read_toml(path, "frame", ScenarioError)
    try:
        return energy.frame_from_table(data.get("frame"))
    except ValueError as err:
        raise ScenarioError(f"{path}: [frame] {err}") from None


def _fault(table: dict, ids: list[str], duration_s: float, where: str) -> Fault:
    kinds = [k.value for k in FaultKind]
    kind = get_value(table, "kind", "str", where, ScenarioError)
    if kind not in kinds:
        raise ScenarioError(f"{where}: kind must be one of {', '.join(kinds)}, got {kind!r}")
    fault = to_dataclass(Fault, {k: v for k, v in table.items() if k != "kind"}, where, ScenarioError, table="fault",
                         kind=FaultKind(kind))
    if fault.vehicle not in ids:
        raise ScenarioError(f"{where}: no vehicle {fault.vehicle!r} in this scenario ({', '.join(ids)})")
    check_number(fault.at_s, f"{where}: fault.at_s", 0.0, duration_s, unit="simulated s (within duration_s)",
                 error=ScenarioError)
    check_number(fault.duration_s, f"{where}: fault.duration_s", 0.0, MAX_DURATION_S,
                 unit="simulated s (0: until the end)", error=ScenarioError)
    if kind in FAULT_VALUE_RANGES:
        check_number(fault.value, f"{where}: fault.value", *FAULT_VALUE_RANGES[kind], unit="%", error=ScenarioError)
    return fault
