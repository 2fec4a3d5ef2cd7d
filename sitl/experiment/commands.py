"""What the experiment runner starts, as data: the ports of each vehicle, each agent's config, the MPI job's
command line (loopback with sleeps, or across the kernel network's namespaces) and which network a run gets.
Pure apart from writing the MPI launcher and hostfile into the run's config folder. The children name the run's
radio by its file (run_channel_path), which the runner writes once before any of them starts."""

from __future__ import annotations

import ipaddress
import math
import sys
from dataclasses import dataclass
from pathlib import Path

from nac_onboard import clock
from nac_onboard.compute import launch
from nac_onboard.radio.transfers import probe_backlog_packets
from nac_onboard.records import kinds
from nac_onboard.tomlfile import dumps_toml
from sitl.experiment.scenario import Scenario
from sitl.network.air import AIR_PREFIX_LENGTH, AirNetwork
from sitl.network.netns import NetworkUnavailable, check_kernel_network
from sitl.vehicle import energy

PORTS_PER_VEHICLE = 10  # ground, companion, peers, throughput server, (master) state feed


def run_channel_path(run_dir: Path) -> Path:
    return kinds.CHANNEL_FILE.at(run_dir)


@dataclass(frozen=True)
class Ports:
    base: int

    def of(self, index: int, slot: int) -> int:
        return self.base + PORTS_PER_VEHICLE * index + slot

    def gcs(self, i: int) -> int:
        return self.of(i, 0)

    def companion(self, i: int) -> int:
        return self.of(i, 1)

    def peers(self, i: int) -> int:
        return self.of(i, 2)

    def throughput(self, i: int) -> int:
        return self.of(i, 3)

    def feed(self) -> int:
        return self.of(0, 4)


def agent_config(scenario: Scenario, index: int, run_dir: Path, ports: Ports,
                 addresses: list[str] | None = None) -> str:
    """One vehicle's agent config. `addresses`: each vehicle's address on a kernel network (the Wi-Fi, shaped by
    the runner); without them every agent is on loopback and the probes emulate the channel themselves."""
    vehicle = scenario.vehicles[index]
    air = addresses or ["127.0.0.1"] * len(scenario.vehicles)
    others = [k for k in range(len(scenario.vehicles)) if k != index]
    master = vehicle.role == "master"
    tool = scenario.throughput.tool if scenario.throughput else "nac"
    # with iperf3 probes the runner serves iperf3 on the workers' probe ports instead of the agents
    throughput = {"server": not master and tool == "nac", "bind": air[index], "port": ports.throughput(index)}
    if master and scenario.throughput:
        p = scenario.throughput
        throughput.update(probe=True, period_s=p.period_s, duration_s=p.duration_s, interval_s=p.interval_s,
                          tool=p.tool, concurrent=p.concurrent,
                          # with a job, from the go it computes from (kinds.START_FILE), as the research's iperf3 ran
                          start_file=str(kinds.START_FILE.at(run_dir)) if scenario.compute else "",
                          emulate_channel="" if addresses else str(run_channel_path(run_dir)),
                          targets=[f"{scenario.vehicles[k].id}={air[k]}:{ports.throughput(k)}" for k in others
                                   if scenario.vehicles[k].role == "worker"])
    listen, send_to = f"{air[index]}:{ports.peers(index)}", [f"{air[k]}:{ports.peers(k)}" for k in others]
    if addresses and scenario.network.air == "medium":
        # one broadcast a period, as the fleet's own default (docs/agent.md), which the medium delivers to whoever
        # is in range: a unicast to each peer (relayed by the access point between workers) is 900 frames a second
        # from 16 vehicles, 52 % of the air measured at 0.5x with wall-clock periods (twice the simulated rate);
        # their broadcasts took 23 % there, at the 1 Mbit/s group rate
        broadcast = ipaddress.ip_interface(f"{addresses[index]}/{AIR_PREFIX_LENGTH}").network.broadcast_address
        listen, send_to = f"0.0.0.0:{ports.peers(0)}", [f"{broadcast}:{ports.peers(0)}"]
    return dumps_toml({
        "vehicle": {"id": vehicle.id, "role": vehicle.role, "sysid": index + 1},
        "autopilot": {"uri": f"udpin:127.0.0.1:{ports.companion(index)}", "link_timeout_s": 3.0},
        "log": {"dir": str(run_dir.parent), "run_id": run_dir.name, "telemetry_hz": 10.0, "tlog": True},
        "peers": {"listen": listen, "key_file": kinds.FLEET_KEY.name, "send_to": send_to, "rate_hz": 2.0,
                  "timeout_s": 3.0,
                  "state_file": str(kinds.PEER_FRESHNESS.at(run_dir, vehicle.id))},
        "state_feed": {"listen": f"127.0.0.1:{ports.feed() if master else ports.of(index, 4)}"},
        "throughput": throughput,
    })


# wall seconds between the master's checkpoints: a master its launcher kills (hydra's proxies kill their ranks when
# mpiexec dies) loses at most this much work; linreg's is 13 numbers, written and renamed in well under 1 ms
CHECKPOINT_S = 1.0


def compute_args(scenario: Scenario, run_dir: Path, ports: Ports, end_at_sim_s: float,
                 kernel: bool = False, workers: list[str] | None = None, resume: bool = False) -> list[str]:
    """The `nac-onboard compute` arguments of the scenario's MPI job: on a kernel network the flight path
    (--emulate none) with the channel's per-transfer overhead as real bytes; otherwise the research's sleeps.
    workers: the ids of the job's workers when not all (a restart without a lost companion); resume: continue from
    the checkpoint."""
    c = scenario.compute
    workers = [w.id for w in scenario.workers] if workers is None else workers
    ids = [scenario.master.id, *workers]
    # without a number of iterations the runner's go (kinds.START_FILE) says when to end
    stop = ["--iterations", str(c.iterations)] if c.iterations else ["--end-at-s", f"{end_at_sim_s:.3f}"]
    if kernel:
        link = ["--emulate", "none", "--pad-bits", f"{scenario.channel.overhead_bits:g}"]
    else:
        link = ["--emulate", "sleep", *probe_backlog_args(scenario)]
    return ["--task", c.task, *stop, "--start-file", str(kinds.START_FILE.at(run_dir)), "--out",
            str(kinds.COMPUTE_LOG.at(run_dir).parent), *link,
            "--channel", str(run_channel_path(run_dir)), "--positions", "feed", "--feed", f"127.0.0.1:{ports.feed()}",
            "--vehicles", ",".join(ids), "--fleet-workers", ",".join(w.id for w in scenario.workers),
            *(["--resume"] if resume else []), "--checkpoint-s", f"{CHECKPOINT_S:g}", "--timeout-s", str(c.timeout_s),
            "--on-missing", c.on_missing, "--allocation", c.allocation, *energy_args(scenario, workers), "--device",
            c.device, "--code-k", str(c.code_k), "--code-s", str(c.code_s), "--code-redundancy",
            f"{c.code_redundancy:g}", "--batch-units",
            str(c.batch_units), "--replan-every", str(c.replan_every), "--link-rates", c.link_rates,
            *(f"--device-of={w.id}={w.device}" for w in scenario.vehicles if w.device), *c.args]


def probe_backlog_args(scenario: Scenario) -> list[str]:
    """A frame-level air's scenario on the sleep network: the queue its probes keep at the master (they send), as
    the job's messages would find it there (nac_onboard.radio.transfers.probe_backlog_packets)."""
    probes, network = scenario.throughput, scenario.network
    if network.air != "medium" or probes is None:
        return []
    backlog = probe_backlog_packets(network.queue_packets, probes.duration_s, probes.period_s,
                                    network.congestion_control)
    return ["--probe-backlog-packets", f"{backlog:g}"] if backlog else []


def energy_args(scenario: Scenario, workers: list[str]) -> list[str]:
    """--allocation energy: each worker's companion pack, full at the start, as the energy it holds (Wh)."""
    if scenario.compute.allocation != "energy":
        return []
    held = [energy.rated_wh(scenario.energy.companion_cells, scenario.companion_mah(w)) for w in scenario.workers
            if w.id in workers]
    return ["--energy-wh", ",".join(f"{wh:.4g}" for wh in held)]


def down_dir(run_dir: Path) -> Path:
    """Where a lost companion's marker lies (its host name): the launcher cannot reach it, as ssh could not."""
    return run_dir / "config" / "down"


def mpi_command(scenario: Scenario, run_dir: Path, ports: Ports, end_at_sim_s: float,
                workers: list[str] | None = None, resume: bool = False) -> list[str]:
    """mpiexec on this machine, one proxy per vehicle (named after it) as on the fleet: a killed rank ends
    only itself (nac_onboard.compute.launch). workers, resume: as compute_args."""
    workers = [w.id for w in scenario.workers] if workers is None else workers
    hosts = [scenario.master.id, *workers]
    return [*launch.mpiexec_command(hosts, run_dir / "config", down_dir=down_dir(run_dir)), sys.executable, "-m",
            "mpi4py", "-m", "nac_onboard.compute",
            *compute_args(scenario, run_dir, ports, end_at_sim_s, workers=workers, resume=resume)]


# UCX's own TCP keepalive (ucx-1.20 src/uct/tcp/tcp_base.h: UCT_TCP_DEFAULT_KEEPALIVE_IDLE, _INTVL; its KEEPCNT
# "auto" leaves the kernel's 9 probes): an idle connection whose peer stays silent 10 + 9 x 2 s is reset.
UCX_KEEPALIVE_IDLE_S, UCX_KEEPALIVE_INTVL_S = 10.0, 2.0


def ucx_keepalive_env(speedup: float) -> dict[str, str]:
    """UCX's keepalive on the run's clock below 1x (above it UCX's own wall seconds, a loaded host's floor): its
    timers run on the wall clock, and at 0.1x its 18 s of silence are 1.8 simulated s, too short for an answer
    queued behind a full transmit queue (measured: an idle keepalive connection beside an 8-stream iperf3 at 1
    Mbit/s, reset after 28.2 wall s), so the MPI job lost its master."""
    return {"UCX_TCP_KEEPIDLE": f"{math.ceil(clock.slowed_s(UCX_KEEPALIVE_IDLE_S, speedup))}s",
            "UCX_TCP_KEEPINTVL": f"{math.ceil(clock.slowed_s(UCX_KEEPALIVE_INTVL_S, speedup))}s"}


def kernel_mpi_command(scenario: Scenario, run_dir: Path, ports: Ports, end_at_sim_s: float, air: AirNetwork,
                       clock_path: Path, speedup: float, workers: list[str] | None = None,
                       resume: bool = False) -> list[str]:
    """mpiexec as on the fleet: started on the master's companion, one rank per vehicle's namespace, over TCP
    only (shared memory would bypass the shaped links), with UCX's keepalive on the run's clock. workers, resume:
    as compute_args."""
    ids = [v.id for v in scenario.vehicles]
    workers = [w.id for w in scenario.workers] if workers is None else workers
    order = [ids.index(scenario.master.id), *(ids.index(w) for w in workers)]
    env = {"UCX_TLS": "tcp,self", "UCX_NET_DEVICES": "air0", "MPIR_CVAR_NOLOCAL": "1", clock.ENV: str(clock_path),
           **ucx_keepalive_env(speedup)}
    mpiexec = launch.mpiexec_command([air.stations[k].netns for k in order], run_dir / "config",
                                     air.stations[order[0]].address, netns=True, env=env)
    return [*air.exec_prefix(order[0]), *mpiexec, sys.executable, "-m", "mpi4py", "-m", "nac_onboard.compute",
            *compute_args(scenario, run_dir, ports, end_at_sim_s, kernel=True, workers=workers, resume=resume)]


def choose_network(requested: str | None, air: str = "htb", modelled_queue: bool = False) -> tuple[str, str]:
    """(network, why): kernel where it can run, else sleep with the reason; a kernel network asked for and
    impossible raises NetworkUnavailable (exit 2) before anything starts. `air`: the scenario's [network] air;
    `modelled_queue`: the sleep network models the queue its probes keep at the master (probe_backlog_args)."""
    # the sleep network runs no queues: a scenario on the frame-level air is told, at the start and in its records
    no_queues = ""
    if air == "medium" and modelled_queue:
        no_queues = ("; the frame-level air's queue modelled, not run: each round of the job's inputs waits for the "
                     "packets the probes keep in the master's queue (3/4 of it, a loss-based TCP's mean) at the links' "
                     "rates, the probes run apart on loopback, and nothing else queues (the kernel network runs the "
                     "air itself)")
    elif air == "medium":
        no_queues = ("; no queues here: the job's messages never wait behind the probes as on the scenario's "
                     "frame-level air (kernel network only), so its iterations are not the testbed's")
    if requested == "sleep":
        return "sleep", ("asked for (--network sleep): transfers sleep bits / capacity, the research's method"
                         + no_queues)
    try:
        check_kernel_network()
    except NetworkUnavailable as err:
        if requested == "kernel":
            raise
        return "sleep", f"the kernel network cannot run here: {err}{no_queues}"
    if air == "medium":
        return "kernel", ("namespaces on a bridge, every frame through the 802.11 medium (a FIFO queue per station, "
                          "channel access, retries) at the live positions' rates")
    return "kernel", "namespaces on a bridge, links shaped by tc and nftables from the live positions"
