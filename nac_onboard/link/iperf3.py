"""Run real iperf3 beside our probe on the same path, to cross-check it: alternating runs of `nac-onboard throughput
probe` against `nac-onboard throughput server` and of `iperf3 --client` against `iperf3 --server`, optionally inside
network namespaces, each compared by its receiver-side rate (the test suite and benchmarks/throughput_vs_iperf3.py).
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass

from nac_onboard.child_process import ReadyProcess
from nac_onboard.errors import OperationFailed
from nac_onboard.link.throughput import BLOCK_BYTES

# pairs tried per run: a transfer of a few MiB on loopback once came back from iperf3 as 0 bit/s (a smoke run in
# the loaded test suite), a reading with no time in it, not a rate to compare
ATTEMPTS = 3


class Iperf3Error(OperationFailed):
    """iperf3 failed or answered with an error."""


def available() -> bool:
    return shutil.which("iperf3") is not None


def nac_server(port: int, netns: str | None = None) -> ReadyProcess:
    command = [sys.executable, "-m", "nac_onboard.cli", "throughput", "server", "--port", str(port)]
    return ReadyProcess(_in(netns, command, cpu=0), "throughput server listening", "nac throughput server")


def iperf3_server(port: int, netns: str | None = None) -> ReadyProcess:
    command = ["iperf3", "--server", "--port", str(port), "--forceflush"]
    return ReadyProcess(_in(netns, command, cpu=0), "Server listening", "iperf3 server")


def _in(netns: str | None, command: list[str], cpu: int | None = None) -> list[str]:
    """Run in a network namespace and/or pinned to one CPU. On loopback both tools are CPU-bound, so each gets the
    same placement: servers on CPU 0, clients on CPU 1."""
    if cpu is not None and shutil.which("taskset") and (os.cpu_count() or 1) >= 2:
        command = ["taskset", "--cpu-list", str(cpu), *command]
    return ["ip", "netns", "exec", netns, *command] if netns else command


def amount_args(duration_s: int | None, nbytes: int | None) -> list[str]:
    return ["--time", str(duration_s)] if nbytes is None else ["--bytes", str(nbytes)]


def nac_rate_bps(host: str, port: int, duration_s: int | None, nbytes: int | None = None,
                 netns: str | None = None) -> float:
    command = [sys.executable, "-m", "nac_onboard.cli", "throughput", "probe", host, "--port", str(port),
               *amount_args(duration_s, nbytes)]
    out = subprocess.run(_in(netns, command, cpu=1), capture_output=True, text=True, timeout=60, check=True)
    return json.loads(out.stdout)["end"]["sum_received"]["bits_per_second"]


def client_result(host: str, port: int, seconds: int, timeout_s: float,
                  started: Callable[[subprocess.Popen], None] | None = None) -> dict:
    """One `iperf3 --client --json` run of whole seconds (iperf3 takes no fractions), as the agent's probes use
    it with `throughput.tool = "iperf3"`: its JSON, or Iperf3Error with iperf3's own error. started, if given, is
    handed the iperf3 process: killing it from another thread ends the probe at once (an Iperf3Error)."""
    command = ["iperf3", "--client", host, "--port", str(port), "--time", str(seconds), "--json",
               "--connect-timeout", "3000"]
    return _client_json(command, f"{host}:{port}", timeout_s, started)


def iperf3_result(host: str, port: int, duration_s: int | None, nbytes: int | None = None,
                  netns: str | None = None) -> dict:
    # The same write size as ours: where the CPU is the bottleneck (loopback) the rate depends on it.
    command = ["iperf3", "--client", host, "--port", str(port), *amount_args(duration_s, nbytes), "--json",
               "--length", str(BLOCK_BYTES)]
    return _client_json(_in(netns, command, cpu=1), f"{host}:{port}", 60.0)


def _client_json(command: list[str], where: str, timeout_s: float,
                 started: Callable[[subprocess.Popen], None] | None = None) -> dict:
    """iperf3's JSON result, or Iperf3Error saying why there is none."""
    try:
        with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as process:
            if started is not None:
                started(process)
            try:
                stdout, stderr = process.communicate(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.communicate()
                raise Iperf3Error(f"iperf3 to {where} gave no result within {timeout_s:g} s") from None
    except OSError as err:
        raise Iperf3Error(f"cannot run iperf3: {err.strerror or err}") from None
    try:
        result = json.loads(stdout)
    except json.JSONDecodeError:
        raise Iperf3Error(f"iperf3 exited {process.returncode} without JSON: {stderr.strip()[-300:]}") from None
    if not isinstance(result, dict) or "error" in result or "end" not in result:
        error = result.get("error") if isinstance(result, dict) else None
        raise Iperf3Error(f"iperf3 to {where}: {error or 'no end section'}")
    return result


@dataclass
class Comparison:
    ours_bps: list[float]
    iperf3_bps: list[float]

    @property
    def ratio(self) -> float:
        """Median of our/iperf3 over adjacent runs: a machine that slows down for a while slows both of a pair."""
        return statistics.median(a / b for a, b in zip(self.ours_bps, self.iperf3_bps, strict=True))

    def describe(self, unit: float, unit_name: str) -> str:
        return (f"ours/iperf3 = {self.ratio:.3f} (medians {statistics.median(self.ours_bps) / unit:.3f} vs "
                f"{statistics.median(self.iperf3_bps) / unit:.3f} {unit_name})")


def _unused_tcp_ports(count: int) -> list[int]:
    """Distinct TCP ports nothing listens on right now (the kernel's picks, held together so they differ; in a
    fresh network namespace every port is free anyway)."""
    sockets = [socket.socket(socket.AF_INET, socket.SOCK_STREAM) for _ in range(count)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def compare(host: str, runs: int, duration_s: int | None = None, nbytes: int | None = None,
            netns_client: str | None = None, netns_server: str | None = None,
            ports: tuple[int, int] | None = None) -> Comparison:
    """Alternating runs of each tool over the same path, receiver-side rates. ports: (ours, iperf3's) servers'."""
    nac_port, iperf_port = ports or _unused_tcp_ports(2)
    result = Comparison([], [])
    with nac_server(nac_port, netns_server), iperf3_server(iperf_port, netns_server):
        for _ in range(runs):
            for _attempt in range(ATTEMPTS):
                ours = nac_rate_bps(host, nac_port, duration_s, nbytes, netns_client)
                theirs = iperf3_result(host, iperf_port, duration_s, nbytes, netns_client)
                theirs_bps = theirs["end"]["sum_received"]["bits_per_second"]
                if ours > 0 and theirs_bps > 0:
                    break
            else:
                raise Iperf3Error(f"{ATTEMPTS} pairs of runs to {host} in a row gave a rate of 0 bit/s")
            result.ours_bps.append(ours)
            result.iperf3_bps.append(theirs_bps)
    return result
