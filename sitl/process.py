"""Run `nac-sitl run` as a child process (for tests and the experiment runner) and stop it cleanly."""

from __future__ import annotations

import os
import selectors
import signal
import subprocess
import sys
import time

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


class SitlProcess:
    """`with SitlProcess(config) as proc:` starts the simulator and waits until it says it is ready."""

    def __init__(self, config: SitlConfig, extra_args: list[str] | None = None, ready_timeout_s: float = 20.0):
        self.config = config
        self.command = [sys.executable, "-m", "sitl.cli", *cli_args(config), *(extra_args or [])]
        self.ready_timeout_s = ready_timeout_s
        self.proc: subprocess.Popen | None = None
        self.banner: list[str] = []

    def start(self) -> SitlProcess:
        self.proc = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        deadline = time.monotonic() + self.ready_timeout_s
        fd = self.proc.stdout.fileno()  # raw reads: a buffered readline would hide lines from select()
        pending = b""
        with selectors.DefaultSelector() as sel:
            sel.register(fd, selectors.EVENT_READ)
            while time.monotonic() < deadline:
                if not sel.select(max(deadline - time.monotonic(), 0.0)):
                    break
                chunk = os.read(fd, 65536)
                if not chunk:
                    break
                *lines, pending = (pending + chunk).split(b"\n")
                self.banner += [line.decode(errors="replace") for line in lines]
                if any(line.startswith(b"nac-sitl ready") for line in lines):
                    return self
        self._end(close=False)
        err = self.proc.stderr.read().decode(errors="replace") if self.proc.stderr else ""
        self._end()
        raise SitlError(f"nac-sitl did not become ready within {self.ready_timeout_s:g} s: {err.strip()}")

    def stop(self, timeout_s: float = 10.0) -> int:
        """SIGINT, then SIGKILL if it has not exited within timeout_s; returns the exit code."""
        return self._end(timeout_s)

    def _end(self, timeout_s: float = 10.0, close: bool = True) -> int:
        proc = self.proc
        if proc is None:
            return 0
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout_s)
        for stream in (proc.stdout, proc.stderr) if close else ():
            if stream:
                stream.close()
        return proc.returncode

    def __enter__(self) -> SitlProcess:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
