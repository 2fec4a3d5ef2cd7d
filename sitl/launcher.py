"""Run `nac-sitl run` as a child process (for tests and the experiment runner) and stop it cleanly."""

from __future__ import annotations

import signal
import sys

from nac_onboard.child_process import ChildStartError, ReadyProcess
from sitl.server import SitlConfig, SitlError


def cli_args(config: SitlConfig) -> list[str]:
    args = ["run", "--vehicles", str(config.vehicles), "--speedup", str(config.speedup),
            "--home", f"{config.home.lat_deg},{config.home.lon_deg},{config.home.alt_m}",
            "--spacing-m", str(config.spacing_m), "--seed", str(config.seed), "--host", config.host,
            "--gcs-base-port", str(config.gcs_base_port), "--companion-base-port", str(config.companion_base_port),
            "--tcp-base-port", str(config.tcp_base_port), "--port-step", str(config.port_step)]
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
