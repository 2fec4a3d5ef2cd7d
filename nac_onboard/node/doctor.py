"""`nac-onboard doctor`: what this node has and whether it is enough for its role. Pure: it judges Facts."""

from __future__ import annotations

from dataclasses import dataclass

from nac_onboard.node.facts import Facts
from nac_onboard.node.mpi_build import UNKNOWN_PREFIX

MIN_PYTHON = (3, 10)
MIN_FREE_BYTES = 500 * 2**20  # a flight's logs are tens of MB; the agent stops logging on a full disk
LOW_FREE_BYTES = 2 * 2**30


@dataclass(frozen=True)
class Finding:
    needed: bool  # True: the role cannot work without it (exit 1); False: advice
    text: str


def assess(facts: Facts, role: str) -> list[Finding]:
    """What is missing or doubtful for `role` (master or worker)."""
    out = []
    if tuple(int(p) for p in facts.python.split(".")[:2]) < MIN_PYTHON:
        out.append(Finding(True, f"Python {facts.python} is too old: NAC needs 3.10 or newer (deploy/install.sh "
                                 "installs a standalone Python where the system's is older)"))
    if facts.mpi_build.startswith(UNKNOWN_PREFIX):
        out.append(Finding(True, f"no MPI: {facts.mpi_build.removeprefix(UNKNOWN_PREFIX)}; every {role} runs a "
                                 "rank of the compute job"))
    if role == "master" and facts.mpiexec is None:
        out.append(Finding(True, "no mpiexec beside this Python or on PATH: the master starts the MPI job"))
    if facts.serial_access not in (None, "ok"):
        out.append(Finding(True, f"autopilot serial port: {facts.serial_access}"))
    if facts.disk_free_bytes < MIN_FREE_BYTES:
        out.append(Finding(True, f"{facts.disk_free_bytes / 2**20:.0f} MB free under {facts.disk_path}: a flight's "
                                 f"logs need at least {MIN_FREE_BYTES / 2**20:.0f} MB"))
    elif facts.disk_free_bytes < LOW_FREE_BYTES:
        out.append(Finding(False, f"only {facts.disk_free_bytes / 2**30:.1f} GB free under {facts.disk_path}"))
    if facts.clock_synced is not True:
        out.append(Finding(False, f"clock {facts.clock_note}: the analysis merges vehicles by unix time, so run "
                                  "chrony on every companion, one serving time over the Wi-Fi (deploy/README.md)"))
    if facts.agent_at_boot not in ("enabled", "static", "alias", "enabled-runtime"):
        out.append(Finding(False, f"the agent does not start at boot (systemctl is-enabled nac-onboard: "
                                  f"{facts.agent_at_boot}): a rebooted {role} rejoins the job once its agent is "
                                  "heard again (deploy/install.sh enables it; the master's `nac-onboard mpi run "
                                  "--keep-going` then starts the job again with it)"))
    if facts.iperf3 is None:
        out.append(Finding(False, "iperf3 is not installed: NAC's own probe works without it, but comparing "
                                  "against iperf3 needs it (apt-get install iperf3)"))
    return out


def report(facts: Facts, role: str, findings: list[Finding]) -> str:
    gib = facts.disk_free_bytes / 2**30
    lines = [
        f"node:   {facts.machine}, {facts.os_name}, glibc {facts.glibc or 'unknown'}"
        + (f", {facts.board}" if facts.board else ""),
        f"python: {facts.python} ({facts.python_path})",
        f"mpi:    {facts.mpi_build}; mpiexec {facts.mpiexec or 'not found'}",
        f"clock:  {facts.clock_note}",
        f"serial: {facts.serial_device}: {facts.serial_access}" if facts.serial_device
        else "serial: not checked (the autopilot is not on a serial port, or no --config)",
        f"disk:   {gib:.1f} GB free under {facts.disk_path}",
        f"boot:   nac-onboard.service {facts.agent_at_boot}",
    ]
    lines += [f"{'MISSING' if f.needed else 'advice'}: {f.text}" for f in findings]
    needed = sum(f.needed for f in findings)
    lines.append(f"doctor: {needed} thing(s) a {role} needs are missing" if needed
                 else f"doctor: this node has what a {role} needs")
    return "\n".join(lines)
