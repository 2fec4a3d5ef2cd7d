"""A NAC experiment described as data: `nac-sitl experiment SCENARIO.toml` reads one of these.

    name = "paper-flight-moving"
    duration_s = 130            # simulated seconds from the missions' start
    max_speedup = 4             # fidelity limit: --speedup above it is refused
    [channel]  preset = "wifi-flight"           # or a TOML file (what `nac-ground logs calibrate` writes)
               background_airtime = 0.2         # any other channel field overrides the preset's
    [compute]  task = "linreg"  iterations = 0  timeout_s = 3.0  args = []   # no [compute]: no MPI job
    [throughput]  period_s = 2.0  duration_s = 0.5  interval_s = 0.1
    [network]  period_s = 0.1  sharing = true   # the kernel network's shaper and the access point's airtime
    [[vehicle]]  id = "master"  role = "master"  mission = "paper-flight-moving/master.plan"
    [[fault]]  at_s = 60  vehicle = "w1"  kind = "link_down"  duration_s = 5

A vehicle's home is its mission's planned home (so the plan and the simulator cannot disagree); a vehicle without
a mission gives `home = [lat, lon, alt_m]` and stays on the ground. Paths are relative to the scenario file.
[channel] is resolved here, once: its preset or file with the table's overrides becomes the scenario's one
radio model (Scenario.channel), which the runner writes to the run directory for every process of the run.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

from missions import MissionFileError, load_mission
from missions.geo import Home
from missions.model import Mission
from nac_onboard.compute.tasks import all_tasks
from nac_onboard.errors import BadInput
from nac_onboard.mavlink.dialect import mission_catalogue
from nac_onboard.radio.channel import ChannelError, ChannelModel
from nac_onboard.radio.files import load_channel
from nac_onboard.tomlfile import get_value, read_toml, to_dataclass
from sitl.experiment.faults import Fault, FaultKind
from sitl.vehicle.params import PARAMS_BY_NAME

SCENARIO_DIR = Path(__file__).resolve().parent.parent / "scenarios"


class ScenarioError(BadInput):
    """A scenario file that cannot be run; the message names the file and the key."""


@dataclass(frozen=True)
class VehiclePlan:
    id: str
    role: str
    home: Home
    mission: Mission | None = None
    mission_path: Path | None = None


@dataclass(frozen=True)
class ComputePlan:
    task: str
    iterations: int = 0  # 0: until the scenario ends
    timeout_s: float = 3.0
    on_missing: str = "incomplete"
    allocation: str = "equal"
    args: tuple[str, ...] = ()


@dataclass(frozen=True)
class ProbePlan:
    period_s: float = 2.0
    duration_s: float = 0.5
    interval_s: float = 0.1
    tool: str = "nac"  # or "iperf3": the real iperf3 between the namespaces (kernel network only)


@dataclass(frozen=True)
class NetworkPlan:
    period_s: float = 0.1  # simulated seconds between shaper updates
    sharing: bool = True  # the master is the access point: what passes through it shares one airtime budget


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
    params: tuple[tuple[str, float], ...] = ()  # autopilot parameters of every vehicle ([params])

    @property
    def master(self) -> VehiclePlan:
        return next(v for v in self.vehicles if v.role == "master")

    @property
    def workers(self) -> list[VehiclePlan]:
        return [v for v in self.vehicles if v.role == "worker"]


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
    path = find_scenario(name_or_path).resolve()
    data = read_toml(path, "scenario", ScenarioError)
    where = str(path)
    duration_s = get_value(data, "duration_s", "float", where, ScenarioError)
    if duration_s <= 0:
        raise ScenarioError(f"{where}: duration_s must be > 0, got {duration_s}")
    vehicles = tuple(_vehicle(v, path, f"{where}: vehicle {k + 1}") for k, v in enumerate(data.get("vehicle", [])))
    roles = [v.role for v in vehicles]
    if roles.count("master") != 1 or len(vehicles) < 2:
        raise ScenarioError(f"{where}: needs one [[vehicle]] with role \"master\" and at least one worker "
                            f"(got roles {roles})")
    ids = [v.id for v in vehicles]
    if len(set(ids)) != len(ids):
        raise ScenarioError(f"{where}: vehicle ids must be unique, got {ids}")
    speedup = data.get("max_speedup", 1.0)
    scenario = Scenario(
        name=get_value(data, "name", "str", where, ScenarioError, path.stem), path=path,
        description=data.get("description", ""),
        duration_s=duration_s, vehicles=vehicles, channel=_channel(data.get("channel", {}), path, where),
        compute=_compute(data["compute"], f"{where}: [compute]") if "compute" in data else None,
        throughput=_probes(data["throughput"], f"{where}: [throughput]") if "throughput" in data else None,
        faults=tuple(_fault(f, ids, f"{where}: fault {k + 1}") for k, f in enumerate(data.get("fault", []))),
        network=_network(data.get("network", {}), f"{where}: [network]"),
        max_speedup=float(speedup), default_speedup=float(data.get("default_speedup", 1.0)),
        notes=tuple(data.get("notes", [])), params=_params(data.get("params", {}), f"{where}: [params]"))
    for k, fault in enumerate(scenario.faults):
        if fault.kind is FaultKind.KILL_WORKER and (scenario.compute is None or fault.vehicle not in
                                            [w.id for w in scenario.workers]):
            raise ScenarioError(f"{where}: fault {k + 1}: kill_worker needs a worker of the MPI job ([compute]), "
                                f"got {fault.vehicle!r}")
    if not 0 < scenario.default_speedup <= scenario.max_speedup:
        raise ScenarioError(f"{where}: default_speedup must be within (0, max_speedup]")
    return scenario


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
    vehicle_id = get_value(table, "id", "str", where, ScenarioError)
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
        return VehiclePlan(vehicle_id, role, home, mission, mission_path)
    home = table.get("home")
    if not (isinstance(home, list) and len(home) == 3 and all(isinstance(x, (int, float)) for x in home)):
        raise ScenarioError(f"{where} ({vehicle_id}): give mission = \"FILE.plan\" or home = [lat, lon, alt_m]")
    return VehiclePlan(vehicle_id, role, Home(*map(float, home)))


def _compute(table: dict, where: str) -> ComputePlan:
    plan = to_dataclass(ComputePlan, table, where, ScenarioError, table="compute")
    tasks = all_tasks()
    if plan.task not in tasks:
        raise ScenarioError(f"{where}: compute.task must be one of {', '.join(tasks)}, got {plan.task!r}")
    return plan


def _probes(table: dict, where: str) -> ProbePlan:
    plan = to_dataclass(ProbePlan, table, where, ScenarioError, table="throughput")
    if not 0 < plan.duration_s <= plan.period_s:
        raise ScenarioError(f"{where}: [throughput] needs 0 < duration_s <= period_s")
    if plan.tool not in ("nac", "iperf3"):
        raise ScenarioError(f"{where}: tool must be \"nac\" or \"iperf3\", got {plan.tool!r}")
    return plan


def _network(table: dict, where: str) -> NetworkPlan:
    plan = to_dataclass(NetworkPlan, table, where, ScenarioError, table="network")
    if not 0.01 <= plan.period_s <= 10.0:
        raise ScenarioError(f"{where}: period_s must be within 0.01..10 simulated seconds, got {plan.period_s}")
    return plan


def _fault(table: dict, ids: list[str], where: str) -> Fault:
    kinds = [k.value for k in FaultKind]
    kind = get_value(table, "kind", "str", where, ScenarioError)
    if kind not in kinds:
        raise ScenarioError(f"{where}: kind must be one of {', '.join(kinds)}, got {kind!r}")
    fault = to_dataclass(Fault, {k: v for k, v in table.items() if k != "kind"}, where, ScenarioError, table="fault",
                         kind=FaultKind(kind))
    if fault.vehicle not in ids:
        raise ScenarioError(f"{where}: no vehicle {fault.vehicle!r} in this scenario ({', '.join(ids)})")
    return fault
