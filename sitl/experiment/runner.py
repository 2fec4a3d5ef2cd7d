"""`nac-sitl experiment SCENARIO`: one NAC experiment in SITL, end to end, with the code that flies.

The simulator (in this process), one `nac-onboard agent` process per vehicle (its own config and log directory),
the missions uploaded, armed and started through the MAVLink client on each vehicle's ground link, the MPI job
under `mpiexec` fed by the master agent's live positions; at the end the vehicles land, everything stops, and
the run directory is analysed into report.md. Whatever happens (Ctrl-C, SIGTERM, a part failing) every child is
stopped, the partial run is analysed, and the outcome says what ended it. SIGKILLed, it leaves nothing running
either: its children die with it (their parent-death signal) and its watchdog kills the rest of the run (MPI's
ranks) and removes its network namespaces (watchdog.py).
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import json
import logging
import os
import secrets
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from missions.model import MavCmd
from nac_onboard import clock
from nac_onboard.child_process import (
    AgentProcess,
    ChildStartError,
    die_with_parent_preexec,
    proc_stat,
    process_running,
)
from nac_onboard.compute.device import load_device_profile
from nac_onboard.compute.launch import kill_leaving_nothing
from nac_onboard.compute.options import options_from_argv
from nac_onboard.compute.supervisor import JobSupervisor
from nac_onboard.errors import BadInput, NacError, OperationFailed, Terminated
from nac_onboard.flight_log import JsonlLog, read_jsonl
from nac_onboard.link.iperf3 import iperf3_server
from nac_onboard.mavlink.client import CommandError, LinkError, VehicleClient
from nac_onboard.mavlink.dialect import M
from nac_onboard.mavlink.mission_transfer import MissionError
from nac_onboard.node.fleet_mpi import workers_heard_at
from nac_onboard.radio.files import save_channel, save_replay
from nac_onboard.radio.replay import ReplayError, ReplayLinks
from nac_onboard.records import Kind, kinds
from sitl.experiment.commands import (
    PORTS_PER_VEHICLE,
    Ports,
    agent_config,
    choose_network,
    compute_args,
    down_dir,
    kernel_mpi_command,
    mpi_command,
    probe_backlog_args,
    run_channel_path,
)
from sitl.experiment.energy_meter import EnergyMeter, namespace_bytes, process_cpu_s
from sitl.experiment.faults import Fault, FaultInjector, FaultKind
from sitl.experiment.progress import VehicleProgress, follow, render_progress
from sitl.experiment.scenario import Scenario
from sitl.experiment.watchdog import TOKEN_ENV, Watchdog
from sitl.network.air import AirNetwork
from sitl.network.medium_air import MediumAir
from sitl.network.netns import NetworkError, forget_connections, pids_in, remove_leftovers, socket_in_netns
from sitl.network.replay import parse_links
from sitl.network.shaper import Shaper
from sitl.server import Sitl, SitlConfig, SitlError
from sitl.vehicle import energy

log = logging.getLogger(__name__)
CLIENT_ERRORS = (OSError, LinkError, CommandError, MissionError)
TAKEOFF_TIMEOUT_S = 60.0  # simulated
COMPUTE_SETUP_TIMEOUT_S = 60.0  # wall: ranks started, data loaded, connections warmed up
HEARTBEAT_WAIT_S = 10.0  # wall at 1x: ten of a vehicle's heartbeats, which it sends at 1 Hz of simulated time
LANDING_SPEEDUP = 20.0  # the simulator alone ran 100 vehicles at 44x on this machine (docs/benchmarks.md, sitl_scale)
CLOCK_PUBLISH_S = 0.1  # wall seconds between publications of the simulator's clock (readers re-read as often)


class Outcome(enum.Enum):
    COMPLETED = (0, "completed")
    INTERRUPTED = (130, "interrupted (Ctrl-C)")
    TERMINATED = (143, "terminated (SIGTERM)")
    COMPUTE_FAILED = (1, "the MPI job failed")
    AGENT_FAILED = (1, "an agent failed")
    MISSION_FAILED = (1, "a mission could not be started")
    SITL_FAILED = (1, "the simulator stopped")
    NETWORK_FAILED = (1, "the kernel network failed")
    BAD_INPUT = (2, "the experiment cannot start")

    @property
    def exit_code(self) -> int:
        return self.value[0]

    @property
    def text(self) -> str:
        return self.value[1]


class ExperimentError(OperationFailed):
    def __init__(self, outcome: Outcome, detail: str):
        super().__init__(f"{outcome.text}: {detail}")
        self.outcome, self.detail = outcome, detail
        self.exit_code = outcome.exit_code


@dataclass
class ExperimentResult:
    outcome: Outcome
    detail: str
    run_dir: Path
    report: Path | None = None
    summary: dict = field(default_factory=dict)


class Experiment:
    def __init__(self, scenario: Scenario, run_dir: Path, speedup: float, base_port: int, out=None,
                 stop: threading.Event | None = None, analyze: bool = True,
                 network: tuple[str, str] = ("sleep", ""), replay: ReplayLinks | None = None,
                 figures: bool = True):
        self.scenario, self.run_dir, self.speedup, self.out = scenario, run_dir, speedup, out or sys.stdout
        self.replay = replay
        self.network, self.network_why = network
        self.air: AirNetwork | None = None
        self.shaper: Shaper | None = None
        self.network_log: JsonlLog | None = None
        self.clock_path = kinds.CLOCK_FILE.at(self.run_dir)
        self._clock_thread: threading.Thread | None = None
        self._clock_stop = threading.Event()
        self.pace = clock.Pace(speedup)
        self.iperf3_probes = bool(scenario.throughput and scenario.throughput.tool == "iperf3")
        self.iperf3_servers: list = []
        self.ports = Ports(base_port)
        self.stop_event = stop or threading.Event()
        self.analyze, self.figures = analyze, figures  # figures: the analysis draws them (else tables and report)
        self.sim: Sitl | None = None
        self.agents: list[AgentProcess] = []
        self.clients: list[VehicleClient] = []
        self.mpi: subprocess.Popen | None = None  # the job's mpiexec now (its supervisor may start another)
        self.job: JobSupervisor | None = None
        self.job_over = False
        self.feed_socket: socket.socket | None = None
        self.mpi_log = None
        self.master_pid: int | None = None  # the MPI master rank's process, once the job is set up
        self.progress = [VehicleProgress(v.id) for v in scenario.vehicles]
        self.pilots: list[threading.Thread] = []
        self.mission_start_sim_s: float | None = None
        self.fault_log: list[dict] = []
        self.step_observers = []  # (t_s, state) callbacks handed to the simulator (tests record the truth)
        self.watchdog: Watchdog | None = None
        self.energy: EnergyMeter | None = None
        self.energy_log: JsonlLog | None = None
        self.rank_pids: dict[str, int] = {}  # vehicle id -> its MPI rank's pid, once its log names it
        self.companions_down: set[int] = set()  # vehicles whose companion computer is lost (faults, empty packs)
        self.frozen: dict[int, list[int]] = {}  # sleep network: a lost companion's stopped processes, by vehicle

    # ---- the run ---------------------------------------------------------------------------------------------
    def run(self) -> ExperimentResult:
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._write_channel()
        outcome, detail = Outcome.COMPLETED, "the scenario ran to its end"
        self._write_record(kinds.EXPERIMENT, scenario=self.scenario.name, path=str(self.scenario.path),
                           speedup=self.speedup, speedup_note=self._speedup_note(), duration_s=self.scenario.duration_s,
                           network={"mode": self.network, "why": self.network_why,
                                    "sharing": self.scenario.network.sharing, "air": self.scenario.network.air,
                                    "period_s": self.scenario.network.period_s,
                                    "congestion_control": self.scenario.network.congestion_control},
                           radio={"name": self.radio.name, "describe": self.radio.describe(),
                                  "sources": self.radio.sources},
                           links=f"replay:{self.replay.source}" if self.replay else "model",
                           probes=dataclasses.asdict(self.scenario.throughput) if self.scenario.throughput else None,
                           vehicles=[{"id": v.id, "role": v.role} for v in self.scenario.vehicles],
                           missions={v.id: [[it.lat_deg, it.lon_deg] for it in v.mission.items
                                            if it.lat_deg or it.lon_deg]
                                     for v in self.scenario.vehicles if v.mission is not None})
        try:
            self._preflight()
            self._start_watchdog()
            self._start()
            self._fly()
        except ExperimentError as err:
            outcome, detail = err.outcome, err.detail
        except Terminated:
            outcome, detail = Outcome.TERMINATED, "stopped by SIGTERM"
        except KeyboardInterrupt:
            outcome, detail = Outcome.INTERRUPTED, "stopped by the operator"
        finally:
            if self.stop_event.is_set() and outcome is Outcome.COMPLETED:
                outcome, detail = Outcome.INTERRUPTED, "stopped by the operator"
            try:
                self._shutdown(land=outcome not in (Outcome.INTERRUPTED, Outcome.TERMINATED))
            finally:
                self._stop_watchdog()
        self._write_record(kinds.EXPERIMENT_ENDED, outcome=outcome.name.lower(), detail=detail, faults=self.fault_log)
        result = ExperimentResult(outcome, detail, self.run_dir)
        if self.analyze:
            result.report, result.summary = self._analyze(outcome)
        return result

    def _write_channel(self) -> None:
        """The run's radio (the scenario's channel; on the sleep network naming the replay table written beside
        it), written once as the channel file every child of the run loads (run_channel_path: agents, MPI
        ranks): the run directory says exactly which model made it. The shaper, in this process, gets the same
        model (self.radio); the scenario stays as it was loaded."""
        radio = self.scenario.channel
        if self.scenario.network.air == "medium":  # every process charges what the frame-level air charges
            radio = dataclasses.replace(radio, mac="802.11")
        path = run_channel_path(self.run_dir)
        path.parent.mkdir(parents=True, exist_ok=True)
        if self.replay is not None and self.network == "sleep":  # the kernel shaper holds the table itself
            table = kinds.REPLAY_TABLE.at(self.run_dir)
            save_replay(self.replay, table)
            radio = dataclasses.replace(radio, replay_file=str(table))
        save_channel(radio, path)
        self.radio = radio

    def _speedup_note(self) -> str:
        limit = f"; at most {self.scenario.max_speedup:.3g}x: {self.scenario.device_limit}" \
            if self.scenario.device_limit else ""
        if self.speedup == 1.0:
            return "real time" + limit
        pace = "sped up" if self.speedup > 1 else "slowed down (time dilation)"
        return (f"{pace}: simulated time ran {self.speedup:g}x wall-clock time, and so did the links, the compute "
                f"job's timeouts and the probes (one clock): results are in simulated seconds{limit}")

    def _write_record(self, kind: Kind, **fields) -> None:
        with JsonlLog(kinds.EXPERIMENT_LOG.at(self.run_dir)) as out:
            out.write(kind, **fields)

    def _preflight(self) -> None:
        """What would only fail minutes later (the MPI job's data) is checked before anything starts."""
        if self.replay is not None:
            try:
                self.replay.check_vehicles([v.id for v in self.scenario.vehicles])
            except ReplayError as err:
                raise ExperimentError(Outcome.BAD_INPUT, str(err)) from None
        if self.replay is not None and self.scenario.network.air == "medium" and self.network == "kernel":
            raise ExperimentError(Outcome.BAD_INPUT, "--links replay gives measured throughput, not the PHY rates "
                                                     "and frame errors the medium needs: use [network] air = \"htb\"")
        if self.iperf3_probes and self.network != "kernel":
            raise ExperimentError(Outcome.BAD_INPUT, "[throughput] tool = \"iperf3\" needs the kernel network: on "
                                                     "loopback iperf3 cannot be paced to the channel model")
        if self.scenario.compute:
            try:
                options_from_argv(compute_args(self.scenario, self.run_dir, self.ports, self.scenario.duration_s,
                                           self.network == "kernel"))
            except NacError as err:
                raise ExperimentError(Outcome.BAD_INPUT, f"the MPI job's options: {err}") from None

    def _start_watchdog(self) -> None:
        """The watchdog first, then the run's token in this process's environment: every child started from here
        on (agents, mpiexec and its ranks, iperf3 servers, tc and nft) inherits it, and the watchdog kills what
        carries it once this process has ended, however it ended."""
        self.watchdog = Watchdog().start()
        os.environ.update(self.watchdog.environ)

    def _stop_watchdog(self) -> None:
        if self.watchdog is not None:
            os.environ.pop(TOKEN_ENV, None)
            self.watchdog.close()  # it finds nothing left after a clean end; it waits for that

    def _start(self) -> None:
        s = self.scenario
        clock.publish(str(self.clock_path), self.speedup, 0.0)
        if self.network == "kernel":
            self._start_air()
        config = SitlConfig(vehicles=len(s.vehicles), speedup=self.speedup,
                            vehicle_homes=tuple(v.home for v in s.vehicles), params=dict(s.params),
                            gcs_base_port=self.ports.gcs(0), companion_base_port=self.ports.companion(0),
                            tcp_base_port=0, port_step=PORTS_PER_VEHICLE,
                            companion_netns=tuple(st.netns for st in self.air.stations) if self.air else (),
                            frames=(s.frame,) * len(s.vehicles) if s.frame else ())
        try:
            self.sim = Sitl(config)
        except (SitlError, NetworkError, OSError) as err:  # e.g. a base port already taken
            raise ExperimentError(Outcome.SITL_FAILED, f"cannot start the simulator: {err}") from None
        self.sim.world.step_observers.extend(self.step_observers)
        self.faults = FaultInjector(self.sim, lambda index: self.agents[index].kill(), self._rank_log,
                                    self._companion)
        self.sim.start()
        self._clock_thread = threading.Thread(target=self._publish_clock, name="clock", daemon=True)
        self._clock_thread.start()
        if self.air is not None:
            self.network_log = JsonlLog(kinds.NETWORK_LOG.at(self.run_dir))
            if isinstance(self.air, MediumAir):
                self.air.record_to(self.network_log)
            self.shaper = Shaper(self.air, self.sim.air_positions, self.radio, self.pace.value,
                                 s.network.period_s, self.network_log, self.replay)
            try:
                self.shaper.start()
            except NetworkError as err:
                raise ExperimentError(Outcome.NETWORK_FAILED, str(err)) from None
        key = kinds.FLEET_KEY.at(self.run_dir)  # a fresh fleet key per run, beside the agents' configs
        key.parent.mkdir(exist_ok=True)
        key.touch(mode=0o600)
        key.write_text(secrets.token_hex(32) + "\n")
        addresses = [st.address for st in self.air.stations] if self.air else None
        if self.iperf3_probes:
            self._start_iperf3_servers()
        for i, vehicle in enumerate(s.vehicles):
            path = kinds.AGENT_CONFIG.at(self.run_dir, vehicle.id)
            path.write_text(agent_config(s, i, self.run_dir, self.ports, addresses))
            agent = AgentProcess(path, env=self._child_env(), prefix=self.air.exec_prefix(i) if self.air else None)
            self.agents.append(agent.launch())  # all at once: each takes a second or so to import and bind
        for vehicle, agent in zip(s.vehicles, self.agents, strict=True):
            try:
                agent.wait_ready()
            except ChildStartError as err:
                raise ExperimentError(Outcome.AGENT_FAILED, f"{vehicle.id}: {err}") from None
        print(f"{s.name}: {len(s.vehicles)} vehicles, {self.speedup:g}x, {len(self.agents)} agents up, "
              f"{self.network} network; logs in {self.run_dir}", file=self.out, flush=True)

    def _child_env(self) -> dict[str, str]:
        return {**os.environ, clock.ENV: str(self.clock_path)}

    def _start_air(self) -> None:
        s = self.scenario
        for name in remove_leftovers():
            print(f"removed network namespace {name}, left by a run that no longer exists", file=self.out)
        ids = [v.id for v in s.vehicles]
        probe_ports = [self.ports.throughput(i) if v.role == "worker" else None for i, v in enumerate(s.vehicles)]
        try:
            if s.network.air == "medium":
                air = MediumAir(ids, ids.index(s.master.id), s.network.sharing, probe_ports, self.speedup,
                                s.network.queue_packets, self.clock_path,
                                congestion_control=s.network.congestion_control,
                                retry_limit=self.radio.retry_limit)
            else:
                air = AirNetwork(ids, ids.index(s.master.id), s.network.sharing, probe_ports, self.speedup,
                                 s.network.congestion_control)
            if self.watchdog is not None:  # before they exist: a SIGKILL while they are being made leaves none
                self.watchdog.watch_namespaces(air.prefix)
            self.air = air.create()
        except NetworkError as err:
            raise ExperimentError(Outcome.NETWORK_FAILED, str(err)) from None

    def _start_iperf3_servers(self) -> None:
        workers = [(i, v) for i, v in enumerate(self.scenario.vehicles) if v.role == "worker"]
        for i, _ in workers:
            self.iperf3_servers.append(iperf3_server(self.ports.throughput(i), self.air.stations[i].netns).launch())
        for (_, vehicle), server in zip(workers, self.iperf3_servers, strict=True):
            try:
                server.wait_ready()
            except ChildStartError as err:
                raise ExperimentError(Outcome.NETWORK_FAILED, f"{vehicle.id}: {err}") from None

    def _publish_clock(self) -> None:
        """The simulator's clock for every process of the run ($NAC_SIM_CLOCK), at its measured pace: with many
        vehicles it can fall behind the speed-up asked for."""
        while not self._clock_stop.wait(CLOCK_PUBLISH_S):
            sim_s = self.sim.paced_t_s()
            try:
                clock.publish(str(self.clock_path), self.pace.add(sim_s), sim_s)
            except OSError as err:
                log.warning("cannot publish the clock: %s", err)

    def _fly(self) -> None:
        s = self.scenario
        if s.compute:  # set up while the missions go up and the vehicles climb; it computes from the go below
            self._start_mpi()
        # every vehicle's port open before the first wait: their heartbeats come in phase, so waiting for each in
        # turn on a port opened just before cost a whole period a vehicle (16 x 8 s of wall time at 0.125x)
        for i in range(len(s.vehicles)):
            self.clients.append(VehicleClient(f"udpin:127.0.0.1:{self.ports.gcs(i)}", sysid=i + 1))
        for i, vehicle in enumerate(s.vehicles):
            client = self.clients[i]
            if vehicle.mission is None:
                continue
            items = vehicle.mission.to_wire()
            self.progress[i].total = len(items) - 1
            try:
                client.wait_heartbeat(self._slowed_s(HEARTBEAT_WAIT_S))
                if client.upload(items) != M.MAV_MISSION_ACCEPTED:
                    raise ExperimentError(Outcome.MISSION_FAILED, f"{vehicle.id}: mission upload refused")
            except CLIENT_ERRORS as err:
                raise ExperimentError(Outcome.MISSION_FAILED, f"{vehicle.id}: {err}") from None
        if s.compute:
            self._wait_for_compute_setup()
        for i, vehicle in enumerate(s.vehicles):
            if vehicle.mission is None:
                continue
            try:
                self.clients[i].command_ok(MavCmd.COMPONENT_ARM_DISARM, 1)
                self.clients[i].command_ok(MavCmd.MISSION_START, 0, 0)
            except CLIENT_ERRORS as err:
                raise ExperimentError(Outcome.MISSION_FAILED, f"{vehicle.id}: {err}") from None
        self.mission_start_sim_s = self.sim.t_s
        self._start_energy()
        for i in range(len(s.vehicles)):
            pilot = threading.Thread(target=follow, args=(self.clients[i], self.progress[i], self.stop_event),
                                     name=f"follow-{s.vehicles[i].id}", daemon=True)
            pilot.start()
            self.pilots.append(pilot)
        self._wait_for_takeoff()
        if s.compute:
            go = json.dumps({"end_at_s": self.mission_start_sim_s + s.duration_s})
            start = kinds.START_FILE.at(self.run_dir)
            partial = start.with_name(start.name + ".partial")
            partial.write_text(go)
            os.replace(partial, start)
        self._watch()

    def _slowed_s(self, wall_s: float) -> float:
        return clock.slowed_s(wall_s, self.speedup)

    def _sim_elapsed_s(self) -> float:
        return self.sim.t_s - (self.mission_start_sim_s or 0.0)

    def _wait_for_takeoff(self) -> None:
        flying = [k for k, v in enumerate(self.scenario.vehicles) if v.mission is not None]
        while not all(1 in self.progress[k].reached for k in flying):
            self._check_children()
            if self._sim_elapsed_s() > TAKEOFF_TIMEOUT_S:
                late = [self.scenario.vehicles[k].id for k in flying if 1 not in self.progress[k].reached]
                raise ExperimentError(Outcome.MISSION_FAILED, f"no take-off within {TAKEOFF_TIMEOUT_S:g} s "
                                                              f"simulated: {', '.join(late)}")
            if self.stop_event.wait(0.05):
                raise KeyboardInterrupt

    def _wait_for_compute_setup(self, timeout_s: float = COMPUTE_SETUP_TIMEOUT_S) -> None:
        """The missions start once the MPI job is set up (its run_started record): its start-up costs wall time,
        which at a speed-up would otherwise be flight without computing, more of it the faster the run. Below 1x
        the wait is longer in proportion: the start-up's connections cross the air on the run's slowed clock."""
        timeout_s = self._slowed_s(timeout_s)
        deadline = time.monotonic() + timeout_s
        path = kinds.COMPUTE_LOG.at(self.run_dir)
        while not (path.exists() and (started := read_jsonl(path).of_kind(kinds.RUN_STARTED))):
            self._check_children()
            if self.mpi.poll() is not None:
                raise ExperimentError(Outcome.COMPUTE_FAILED, f"mpiexec exited {self.mpi.returncode} while setting "
                                                              f"up (see {kinds.MPIEXEC_LOG.at(self.run_dir)})")
            if time.monotonic() > deadline:
                raise ExperimentError(Outcome.COMPUTE_FAILED, f"the MPI job was not set up within {timeout_s:g} s")
            if self.stop_event.wait(0.02):
                raise KeyboardInterrupt
        self.master_pid = started[0].get("pid")

    def _start_mpi(self) -> None:
        """The MPI job under its supervisor, which starts it again from its checkpoint when a companion is lost or
        back (nac_onboard/compute/supervisor.py), as `nac-onboard mpi run --keep-going` does on the fleet."""
        s = self.scenario
        self.end_at_sim_s = self.sim.t_s + TAKEOFF_TIMEOUT_S + s.duration_s  # the go gives the real end
        kinds.MPIEXEC_LOG.at(self.run_dir).parent.mkdir(exist_ok=True)
        self.mpi_log = open(kinds.MPIEXEC_LOG.at(self.run_dir), "ab")  # noqa: SIM115 (closed at shutdown)
        master = s.vehicles.index(s.master)
        if self.air is not None:
            self.air.wait_for_carrier()  # MPI's transport picks its devices once, at start
            self.feed_socket = socket_in_netns(self.air.stations[master].netns, socket.AF_INET, socket.SOCK_DGRAM)
        else:
            self.feed_socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.job = JobSupervisor([w.id for w in s.workers], self._launch_mpi, self._workers_heard,
                                 kinds.COMPUTE_LOG.at(self.run_dir).parent, s.compute.task, lambda: self.sim.t_s,
                                 scratch_noted=self.watchdog.remove_at_end if self.watchdog else None)
        self.job.begin()
        print(f"MPI job started (pid {self.mpi.pid}): {s.compute.task}, {len(s.workers)} workers", file=self.out,
              flush=True)

    def _launch_mpi(self, workers: list[str], resume: bool) -> subprocess.Popen:
        """mpiexec for the job's supervisor: these workers, from the checkpoint or not."""
        if self.air is not None:
            command = kernel_mpi_command(self.scenario, self.run_dir, self.ports, self.end_at_sim_s, self.air,
                                         self.clock_path, self.speedup, workers, resume)
        else:
            command = mpi_command(self.scenario, self.run_dir, self.ports, self.end_at_sim_s, workers, resume)
        self.mpi_log.write(f"---- nac-sitl: mpiexec for {', '.join(workers)}{' (--resume)' if resume else ''}\n"
                           .encode())
        self.mpi_log.flush()
        self.mpi = subprocess.Popen(command, stdout=self.mpi_log, stderr=subprocess.STDOUT, start_new_session=True,
                                    env=self._child_env(), preexec_fn=die_with_parent_preexec(signal.SIGTERM))
        self.rank_pids.clear()
        if self.mission_start_sim_s is not None:  # a start again, not the first
            print(f"MPI job started again (pid {self.mpi.pid}) with {', '.join(workers)}"
                  f"{', from its checkpoint' if resume else ''} at t={self._sim_elapsed_s():.1f} s", file=self.out,
                  flush=True)
        return self.mpi

    def _workers_heard(self) -> dict[str, str] | None:
        """The workers the master's agent hears now (its state feed), as the fleet's supervisor asks it."""
        return workers_heard_at(f"127.0.0.1:{self.ports.feed()}", 0.2, self.feed_socket)

    def _watch(self) -> None:
        pending = sorted(self.scenario.faults, key=lambda f: f.at_s)
        active: list[tuple[float, Fault]] = []
        next_display = time.monotonic()
        while self._sim_elapsed_s() < self.scenario.duration_s:
            now = self._sim_elapsed_s()
            while pending and pending[0].at_s <= now:
                fault = pending.pop(0)
                self._inject(fault, True)
                if fault.duration_s > 0:
                    active.append((fault.at_s + fault.duration_s, fault))
            for item in [a for a in active if a[0] <= now]:
                active.remove(item)
                self._inject(item[1], False)
            self._check_children()
            self._meter()
            if self.job_over and self.scenario.compute.iterations:
                print(f"MPI job finished its {self.scenario.compute.iterations} iterations at "
                      f"t={now:.1f} s", file=self.out, flush=True)
                return
            if time.monotonic() >= next_display:
                line = render_progress(now, self.progress, self.run_dir, self.scenario.master.id)
                print(line, file=self.out, flush=True)
                next_display += 1.0
            if self.stop_event.wait(0.05):
                raise KeyboardInterrupt

    def _start_energy(self) -> None:
        s = self.scenario
        fleet = s.compute.device if s.compute is not None else "host"
        slowdowns = [1.0 if (v.device or fleet) == "host" else load_device_profile(v.device or fleet).slowdown
                     for v in s.vehicles]
        self.energy_log = JsonlLog(kinds.ENERGY_LOG.at(self.run_dir))
        frames = [s.frame.name if s.frame else energy.FRAME_NAMES[int(self.sim.world.params.get(i, "NAC_FRAME"))]
                  for i in range(len(s.vehicles))]
        self.energy = EnergyMeter([v.id for v in s.vehicles], s.energy,
                                  [s.companion_mah(v) for v in s.vehicles], frames,
                                  self.energy_log, slowdowns, radio_counted=self.air is not None)
        self._meter()

    def _meter(self) -> None:
        """The energy meter's tick; a companion pack that emptied stops its agent, its rank and its radio."""
        vehicles = self.scenario.vehicles
        t_s, packs = self.sim.batteries()  # the flight packs and their time, taken at one step
        now_s = t_s - self.mission_start_sim_s
        if not self.energy.due(now_s):
            return
        cpu_s = [process_cpu_s(self._rank_pid(v.id)) for v in vehicles]
        net = [namespace_bytes(self.agents[i].proc.pid if self.agents[i].alive() else None) if self.air else None
               for i in range(len(vehicles))]
        for i in self.energy.tick(now_s, packs, cpu_s, net, self.pace.value(), self._station_rates_bps()):
            self._companion_off(i, now_s)

    def _station_rates_bps(self) -> list[float | None] | None:
        """Each station's link now (the shaper's last rates, bits per simulated second): a worker's to the master,
        the master's the harmonic mean of its links in range (its bytes take each link's time); None out of range."""
        state = self.shaper.last if self.shaper is not None else None
        if state is None:
            return None
        n, m = len(self.scenario.vehicles), self.scenario.vehicles.index(self.scenario.master)
        rates: list[float | None] = []
        for i in range(n):
            links = [float(state.rate_bps[m, j]) for j in range(n) if j != m] if i == m else [
                float(state.rate_bps[i, m])]
            links = [r for r in links if r > 0]
            rates.append(len(links) / sum(1.0 / r for r in links) if links else None)
        return rates

    def _rank_pid(self, vehicle_id: str) -> int | None:
        """The vehicle's MPI rank's pid: the master's from the job's start, a worker's from its rank log."""
        if self.scenario.compute is None:
            return None
        if vehicle_id == self.scenario.master.id:
            return self.master_pid
        if vehicle_id not in self.rank_pids:
            path = self._rank_log(vehicle_id)
            started = read_jsonl(path).of_kind(kinds.WORKER_STARTED) if path.exists() else []
            if not started:
                return None
            self.rank_pids[vehicle_id] = int(started[-1]["pid"])
        return self.rank_pids[vehicle_id]

    def _companion(self, index: int, up: bool) -> None:
        """lose_companion / reboot_companion: the vehicle's companion computer gone, or back."""
        if not up:
            self._lose_companion(index)
            return
        self.companions_down.discard(index)
        vehicle = self.scenario.vehicles[index]
        self._kill_frozen(index)
        if self.air is not None:
            self.air.silence(index, False)
            if self.iperf3_probes and vehicle.role == "worker":
                k = [v.role for v in self.scenario.vehicles[:index]].count("worker")
                self.iperf3_servers[k] = iperf3_server(self.ports.throughput(index),
                                                       self.air.stations[index].netns).launch()
        agent = AgentProcess(kinds.AGENT_CONFIG.at(self.run_dir, vehicle.id), env=self._child_env(),
                             prefix=self.air.exec_prefix(index) if self.air else None)
        self.agents[index] = agent.launch()  # as systemd's Restart= would; ready is awaited by the job's restart
        with contextlib.suppress(FileNotFoundError):
            (down_dir(self.run_dir) / vehicle.id).unlink()

    def _lose_companion(self, index: int) -> list[str]:
        """Everything on the vehicle's companion stops at once, as in a brown-out, and sends nothing more (no FIN,
        no RST): on the kernel network its radio goes down first, then every process in its namespace is killed
        and its connections forgotten; on the sleep network, where its sockets are the host's, its agent, MPI rank
        and the rank's proxy are frozen (SIGSTOP) until it reboots or the run ends, and then killed (its stale
        connections reset then, as a rebooted computer's do). Returns what stopped."""
        vehicle = self.scenario.vehicles[index]
        self.companions_down.add(index)
        stopped = []
        if self.air is not None:
            self.air.silence(index)
            stopped.append("radio")
        down_dir(self.run_dir).mkdir(parents=True, exist_ok=True)
        (down_dir(self.run_dir) / vehicle.id).touch()  # the sleep network's launcher cannot reach it now
        pids = pids_in(self.air.stations[index].netns) if self.air is not None else []
        if self.agents[index].alive():
            pids.append(self.agents[index].proc.pid)
            stopped.append("agent")
        if self.scenario.compute is not None:
            rank = self.master_pid if vehicle.role == "master" else self._rank_pid(vehicle.id)
            proxy = _parent_if(rank, "hydra_pmi_proxy") if rank else None
            pids += [p for p in (rank, proxy) if p and p not in pids]
            if rank and process_running(rank):
                stopped.append("rank")
            self.rank_pids.pop(vehicle.id, None)  # a rank started again has another pid
        if self.air is None:
            self.frozen[index] = pids
            for pid in pids:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGSTOP)
        else:
            kill_leaving_nothing(pids)
            # and no connection state: a dead computer retransmits no FIN when it is back
            forget_connections(self.air.stations[index].netns)
        return stopped

    def _kill_frozen(self, index: int) -> None:
        """A lost companion's processes that were frozen (sleep network) killed, its agent reaped: it reboots, or
        the run ends."""
        if index not in self.frozen:
            return
        kill_leaving_nothing(self.frozen.pop(index))
        self.agents[index].kill()

    def _companion_off(self, index: int, now_s: float) -> None:
        vehicle = self.scenario.vehicles[index]
        stopped = self._lose_companion(index)
        self._note_fault(vehicle.id, FaultKind.LOSE_COMPANION, True)
        self.energy_log.write(kinds.BATTERY_EMPTY, t_sim_s=round(now_s, 3), vehicle=vehicle.id, pack="companion",
                              stopped=stopped)
        print(f"energy: {vehicle.id}'s companion pack is empty at t={now_s:.1f} s: {', '.join(stopped)} stopped",
              file=self.out, flush=True)
        if vehicle.role == "master" and self.scenario.compute is not None:
            raise ExperimentError(Outcome.COMPUTE_FAILED, f"the master's companion pack ran out at t={now_s:.1f} s: "
                                                          "the MPI job lost its master")

    def _check_children(self) -> None:
        if not self.sim.alive:
            raise ExperimentError(Outcome.SITL_FAILED, "the simulation loop stopped (see the log)")
        for agent, vehicle in zip(self.agents, self.scenario.vehicles, strict=False):
            if not agent.alive() and not self._killed_on_purpose(vehicle.id, FaultKind.KILL_AGENT) and \
                    self.scenario.vehicles.index(vehicle) not in self.companions_down:
                raise ExperimentError(Outcome.AGENT_FAILED, f"{vehicle.id}'s agent exited "
                                                            f"({agent.proc.returncode}): {agent.stderr_text()[-500:]}")
        if self.job is not None and not self.job_over:
            code = self.job.poll()  # a job that ended without its end is started again, from its checkpoint
            if self.job.launch is not None and self.job.launch.master_pid:
                self.master_pid = self.job.launch.master_pid
            if code is not None:
                self.job_over = True
                if code != 0:
                    raise ExperimentError(Outcome.COMPUTE_FAILED, f"the MPI job could not be kept going (exit "
                                                                  f"{code}; see {kinds.MPIEXEC_LOG.at(self.run_dir)} "
                                                                  f"and {kinds.JOB_LOG.at(self.run_dir)})")

    def _killed_on_purpose(self, vehicle_id: str, kind: FaultKind) -> bool:
        return any(f["vehicle"] == vehicle_id and f["kind"] == kind.value for f in self.fault_log)

    def _inject(self, fault: Fault, on: bool) -> None:
        index = next(k for k, v in enumerate(self.scenario.vehicles) if v.id == fault.vehicle)
        self.faults.apply(fault, index, on)
        self._note_fault(fault.vehicle, fault.kind, on)

    def _note_fault(self, vehicle_id: str, kind: FaultKind, on: bool) -> None:
        record = {"t_sim_s": round(self._sim_elapsed_s(), 3), "vehicle": vehicle_id, "kind": kind.value,
                  "state": "on" if on else "off"}
        self.fault_log.append(record)
        self._write_record(kinds.FAULT, vehicle=vehicle_id, fault=kind.value, state=record["state"],
                           t_sim_s=record["t_sim_s"])  # as it happens: the live view reads it
        print(f"fault: {kind.value} {record['state']} for {vehicle_id} at t={record['t_sim_s']:.1f} s",
              file=self.out, flush=True)

    def _rank_log(self, vehicle_id: str) -> Path:
        rank = 1 + [w.id for w in self.scenario.workers].index(vehicle_id)
        return kinds.RANK_LOG.at(self.run_dir, rank=rank)

    # ---- the end ---------------------------------------------------------------------------------------------
    def _shutdown(self, land: bool) -> None:
        self.stop_event.set()  # the progress followers stop reading
        # at the scenario's end the MPI job is finishing its own --duration-s: let it write its summary
        # (its last iteration may wait out the job's timeout, which is simulated seconds)
        self._stop_mpi(grace_s=self._slowed_s(self.scenario.compute.timeout_s + 2.0)
                       if land and self.scenario.compute else 0.0)
        if self.job is not None:
            self.job.stop()
        for index in list(self.frozen):  # after the job's end: their connections reset when they die
            self._kill_frozen(index)
        if self.feed_socket is not None:
            self.feed_socket.close()
        for t in self.pilots:
            t.join(2.0)
        for agent in self.agents:  # their records end with the scenario: the landing below is not part of it
            agent.signal_stop()
        for agent in self.agents:
            agent.stop(5.0)
        for server in self.iperf3_servers:
            server.stop(2.0)
        if self.shaper is not None:
            self.shaper.stop()
        if land and self.sim is not None and self.sim.alive:
            self._land()
        for client in self.clients:
            client.close()
        self._clock_stop.set()
        if self.sim is not None:
            self.sim.stop()
        if self.air is not None:  # whatever still runs inside is killed with its namespace
            self.air.close()
        if self.network_log is not None:
            self.network_log.close()
        if self.energy_log is not None:
            self.energy_log.close()
        if self.mpi_log is not None:
            self.mpi_log.close()

    def _stop_mpi(self, grace_s: float) -> None:
        if self.mpi is None:
            return
        try:
            self.mpi.wait(grace_s)
        except subprocess.TimeoutExpired:
            pass
        if self.mpi.poll() is not None:
            return
        try:
            os.killpg(self.mpi.pid, signal.SIGTERM)  # mpiexec and every rank: its own session
            self.mpi.wait(5.0)
        except subprocess.TimeoutExpired:
            os.killpg(self.mpi.pid, signal.SIGKILL)
            self.mpi.wait(5.0)
        except ProcessLookupError:
            pass

    def _land(self, timeout_s: float = 60.0) -> None:
        """LAND every airborne vehicle and wait (simulated time) for the ground: the disarm on landing ends it. Only
        the simulator runs by then, so it lands at LANDING_SPEEDUP (or the run's, if faster) as far as the host
        keeps up: at 1x the descent from the research's 9.8 m took 21 s of the operator's time for nothing."""
        self.sim.set_speedup(max(self.speedup, LANDING_SPEEDUP))
        for i, client in enumerate(self.clients):
            if self.sim.truth(i)["armed"]:
                try:
                    client.command(MavCmd.NAV_LAND, timeout_s=1.0)
                except CLIENT_ERRORS as err:
                    log.warning("land %s: %s", self.scenario.vehicles[i].id, err)
        deadline = self.sim.t_s + timeout_s
        while self.sim.t_s < deadline and any(self.sim.truth(i)["armed"] for i in range(len(self.clients))):
            time.sleep(0.05)
        for i in range(len(self.clients)):
            self.progress[i].landed = not self.sim.truth(i)["armed"]

    def _analyze(self, outcome: Outcome) -> tuple[Path | None, dict]:
        from ground.logs.report import analyze_run
        from ground.logs.runlog import RunDirError

        try:
            tables = analyze_run(self.run_dir, self.run_dir / kinds.ANALYSIS_DIR,
                                 report_path=kinds.REPORT.at(self.run_dir), draw_figures=self.figures)
        except RunDirError as err:
            if self.sim is not None:  # a run stopped before its simulator started has nothing to analyse: its
                print(f"analysis: {err}", file=self.out)  # failure alone says why
            return None, {}
        return kinds.REPORT.at(self.run_dir), tables.summary


def _parent_if(pid: int, name: str) -> int | None:
    """pid's parent process, if its name is `name` (a rank's hydra proxy)."""
    try:
        ppid = int(proc_stat(pid)[1])
        return ppid if Path(f"/proc/{ppid}/comm").read_text().strip() == name else None
    except (OSError, ValueError, IndexError):
        return None


def default_run_dir(scenario: Scenario) -> Path:
    return Path("runs") / f"{scenario.name}-{time.strftime('%Y%m%dT%H%M%S')}"


def run_scenario(scenario: Scenario, run_dir: Path | None, speedup: float, base_port: int = 14550,
                 out=None, stop: threading.Event | None = None, analyze: bool = True,
                 network: str | None = None, links: str = "model", view: str | None = None,
                 figures: bool = True) -> ExperimentResult:
    """Run one scenario and print its final summary; the result says how it ended and where the report is.
    network: "kernel", "sleep" or None (kernel where it can run). links: "model" (the radio model) or
    "replay:RUN" (a recorded run's measured throughput per pair). view: HOST:PORT to serve the live page on
    (its screenshot at the end goes into the run directory as view.png). figures: False for an analysis of tables
    and report alone."""
    out = out or sys.stdout
    replay = parse_links(links)
    chosen = choose_network(network, scenario.network.air, bool(probe_backlog_args(scenario)))
    if chosen[0] != network:
        print(f"network: {chosen[0]} ({chosen[1]})", file=out, flush=True)
    run_dir = Path(run_dir) if run_dir else default_run_dir(scenario)
    if kinds.EXPERIMENT_LOG.at(run_dir).exists():  # appended to, its logs would hold two runs the analysis mixes
        raise BadInput(f"{run_dir}: holds a run already ({kinds.EXPERIMENT_LOG.name}): give another --out, or "
                       "remove it")
    experiment = Experiment(scenario, run_dir, speedup, base_port, out, stop, analyze, chosen, replay, figures)
    viewer = None
    if view:
        from ground.view.serve import ViewThread
        from ground.view.server import ViewServer

        run_dir.mkdir(parents=True, exist_ok=True)
        viewer = ViewThread(ViewServer(run_dir, live=True, title=scenario.name), view)
        print(f"view: {viewer.start()}", file=out, flush=True)
    try:
        result = experiment.run()
    finally:
        if viewer is not None:
            save_screenshot(viewer, run_dir, out)
            viewer.stop()
    print(final_summary(result), file=out, flush=True)
    return result


def save_screenshot(viewer, run_dir: Path, out) -> None:
    from ground.view.serve import chromium, screenshot

    if chromium() is None:
        print("view: no Chromium here, so no screenshot (Debian: apt-get install chromium)", file=out, flush=True)
        return
    try:
        screenshot(viewer.url, kinds.VIEW_PNG.at(run_dir))
        print(f"view: {kinds.VIEW_PNG.at(run_dir)}", file=out, flush=True)
    except NacError as err:
        print(f"view: no screenshot: {err}", file=out, flush=True)


def final_summary(result: ExperimentResult) -> str:
    s = result.summary
    lines = [f"{result.run_dir.name}: {result.outcome.text} ({result.detail})"]
    if "iterations" in s:
        lines.append(f"  compute: {s['iterations']} iterations, mean {s['mean_iteration_s']:.3f} s, "
                     f"{s.get('iterations_per_min') or 0:.1f} per minute; "
                     f"absent iterations {s.get('absent_iterations')}")
    if s.get("final_cost") is not None:
        lines.append(f"  training cost {s['first_cost']:.4f} -> {s['final_cost']:.4f}")
    if "probes" in s:
        lines.append(f"  throughput: {s['probes']} probes ({s['failed_probes']} failed), mean "
                     f"{s['mean_throughput_mbps']:.2f} Mbit/s, above {s['threshold_mbps']:g} Mbit/s up to "
                     f"{s['range_above_threshold_m']} m")
    lines.append(f"  report: {result.report}" if result.report else "  report: none (nothing to analyse)")
    return "\n".join(lines)
