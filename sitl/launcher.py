"""Run `nac-sitl run` as a child process (for tests and the experiment runner) and stop it cleanly."""

from __future__ import annotations

import random
import signal
import socket
import sys

from nac_onboard.child_process import ChildStartError, ReadyProcess
from sitl.server import SitlConfig, SitlError


def cli_args(config: SitlConfig) -> list[str]:
    args = ["run", "--vehicles", str(config.vehicles), "--speedup", str(config.speedup),
            "--home", f"{config.home.lat_deg},{config.home.lon_deg},{config.home.alt_m}",
            "--spacing-m", str(config.spacing_m), "--seed", str(config.seed), "--host", config.host,
            "--gcs-base-port", str(config.gcs_base_port), "--companion-base-port", str(config.companion_base_port),
            "--tcp-base-port", str(config.tcp_base_port), "--tcp-bind", config.tcp_bind,
            "--port-step", str(config.port_step)]
    for host, port in config.extra_outs:
        args += ["--out", f"{host}:{port}"]
    return args


class SitlProcess(ReadyProcess):
    """`with SitlProcess(config) as proc:` starts the simulator and waits until it says it is ready."""

    def __init__(self, config: SitlConfig, extra_args: list[str] | None = None, ready_timeout_s: float = 20.0):
        self.config = config
        command = [sys.executable, "-m", "sitl.cli", *cli_args(config), *(extra_args or [])]
        super().__init__(command, "nac-sitl ready", "nac-sitl", ready_timeout_s, signal.SIGINT)

    @property
    def banner(self) -> list[str]:
        return list(self.output)

    def start(self) -> SitlProcess:
        try:
            return super().start()
        except ChildStartError as err:
            raise SitlError(str(err)) from None


# ---- free loopback ports for local SITL / agent processes (tests, benchmarks) ---------------------------------
def _free(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _port_range() -> tuple[int, int]:
    """Ports to hand out: below the kernel's ephemeral range, so a socket bound to port 0 (the SITL's links, any
    client) cannot take a port that was handed out and is about to be bound."""
    try:
        with open("/proc/sys/net/ipv4/ip_local_port_range") as f:
            low = int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    return 10000, max(low, 12000)


# every port this process has handed out: free when handed out, but bound only later by whoever it went to (an
# agent binds its SITL companion port when it starts), so never handed out twice (a clean-clone CI run, 2026-11-28:
# an agent's state feed took the companion port of the SITL the same test had been given, and the second agent
# found it in use)
_handed_out: set[int] = set()


def _usable(port: int) -> bool:
    return port not in _handed_out and _free(port, socket.SOCK_DGRAM) and _free(port, socket.SOCK_STREAM)


def free_port() -> int:
    """A loopback port free for both UDP and TCP right now, for a local SITL or agent process to bind."""
    first, end = _port_range()
    for _ in range(200):
        port = random.randrange(first, end)
        if _usable(port):
            _handed_out.add(port)
            return port
    raise RuntimeError("no free port found")


def allocate_base_port(vehicles: int, step: int = 10, slots: int = 2) -> int:
    """A base port B on loopback with B+step*i+k free (UDP and TCP) for every vehicle i and slot k < slots (ground,
    companion, ...): the port block of a local SITL (SitlConfig's gcs/companion base ports and port_step)."""
    first, end = _port_range()
    for _ in range(200):
        base = random.randrange(first, end - step * vehicles, 2)
        ports = [base + step * i + k for i in range(vehicles) for k in range(slots)]
        if all(_usable(p) for p in ports):
            _handed_out.update(ports)
            return base
    raise RuntimeError("no free port range found")
