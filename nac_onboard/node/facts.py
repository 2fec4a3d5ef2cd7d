"""What this companion computer has, read off the machine: Python, glibc, the MPI build and its mpiexec, the
clock's synchronisation, the autopilot's serial port, free disk, whether the agent starts at boot. Each reading
says what it found or why it could not tell; nothing here decides whether that is enough (doctor.py does)."""

from __future__ import annotations

import ctypes
import os
import platform
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from nac_onboard.node.mpi_build import mpi_build

TIME_ERROR = 5  # adjtimex's answer while the kernel clock is not synchronised (STA_UNSYNC)
TIMEX_BYTES = 256  # struct timex is 208 bytes on LP64 Linux; the rest is slack
TIMEX_ESTERROR_OFFSET = 32  # modes (int, padded), offset, freq, maxerror, then esterror (long, microseconds)


@dataclass
class Facts:
    machine: str
    os_name: str
    glibc: str | None
    board: str | None
    python: str
    python_path: str
    mpi_build: str
    mpiexec: str | None
    clock_synced: bool | None
    clock_note: str
    serial_device: str | None = None  # the autopilot's port, when the config names one
    serial_access: str | None = None  # "ok", or what is wrong with it
    disk_path: str = "."
    disk_free_bytes: int = 0
    iperf3: str | None = None
    agent_at_boot: str = "unknown"  # `systemctl is-enabled nac-onboard.service`: enabled, disabled, not installed...


def read_facts(serial_device: str | None = None, disk_path: str | Path = ".") -> Facts:
    synced, clock_note = clock_state()
    disk = Path(disk_path)
    while not disk.exists() and disk != disk.parent:  # the log directory may not exist yet: its filesystem
        disk = disk.parent
    facts = Facts(machine=platform.machine(), os_name=os_name(), glibc=glibc_version(), board=board_model(),
                  python=platform.python_version(), python_path=sys.executable, mpi_build=mpi_build(),
                  mpiexec=mpiexec(), clock_synced=synced, clock_note=clock_note, disk_path=str(disk),
                  disk_free_bytes=shutil.disk_usage(disk).free, iperf3=shutil.which("iperf3"),
                  agent_at_boot=agent_at_boot())
    if serial_device:
        facts.serial_device, facts.serial_access = serial_device, serial_access(serial_device)
    return facts


def glibc_version() -> str | None:
    try:
        return os.confstr("CS_GNU_LIBC_VERSION").split()[-1]  # "glibc 2.36"
    except (ValueError, OSError, AttributeError, IndexError):
        return None  # musl, or not Linux


def os_name() -> str:
    try:
        for line in Path("/etc/os-release").read_text().splitlines():
            if line.startswith("PRETTY_NAME="):
                return line.partition("=")[2].strip().strip('"')
    except OSError:
        pass
    return platform.platform()


def board_model() -> str | None:
    """The Jetson's model and L4T release when this is one (JetPack's files), else the device tree's model."""
    parts = []
    for path in ("/proc/device-tree/model", "/etc/nv_tegra_release"):
        try:
            text = Path(path).read_text(errors="replace").replace("\x00", "").strip()
        except OSError:
            continue
        if text:
            parts.append(text.splitlines()[0].lstrip("# "))
    return "; ".join(parts) or None


def mpiexec() -> str | None:
    beside = Path(sys.executable).parent / "mpiexec"
    return str(beside) if beside.exists() else shutil.which("mpiexec")


def clock_state() -> tuple[bool | None, str]:
    """Whether the kernel clock is synchronised (adjtimex, whatever daemon disciplines it) and, with chrony,
    its view: reference, stratum, offset."""
    synced, note = None, "unknown (adjtimex unavailable)"
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        timex = ctypes.create_string_buffer(TIMEX_BYTES)  # modes = 0: read only
        state = libc.adjtimex(timex)
        if state >= 0:
            synced = state != TIME_ERROR
            esterror_us = ctypes.c_long.from_buffer(timex, TIMEX_ESTERROR_OFFSET).value
            note = (f"synchronised (kernel), estimated error {esterror_us / 1000:.1f} ms" if synced
                    else "not synchronised (kernel): no NTP/chrony disciplines this clock")
    except (OSError, AttributeError):
        pass
    chronyc = shutil.which("chronyc")
    if chronyc:
        try:
            out = subprocess.run([chronyc, "-c", "tracking"], capture_output=True, text=True, timeout=3.0).stdout
            fields = out.strip().split(",")
            if len(fields) >= 14:
                note += f"; chrony: {fields[13]}, reference {fields[1] or fields[0]}, stratum {fields[2]}, " \
                        f"offset {float(fields[4]) * 1000:+.2f} ms"
        except (OSError, subprocess.TimeoutExpired, ValueError):
            note += "; chronyc did not answer"
    return synced, note


def agent_at_boot() -> str:
    """Whether systemd starts the agent at boot (a rebooted companion rejoins the job once its agent is heard)."""
    systemctl = shutil.which("systemctl")
    if systemctl is None:
        return "unknown (no systemctl)"
    try:
        done = subprocess.run([systemctl, "is-enabled", "nac-onboard.service"], capture_output=True, text=True,
                              timeout=5.0)
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"unknown ({err})"
    state = done.stdout.strip()
    if state:
        return state
    return "not installed" if "No such file" in done.stderr else f"unknown ({done.stderr.strip()[:80]})"


def serial_access(device: str) -> str:
    path = Path(device)
    if not path.exists():
        return f"{device} does not exist (is the autopilot wired, and the UART enabled?)"
    if not os.access(path, os.R_OK | os.W_OK):
        return (f"{device}: this user may not read and write it (add the user to the device's group, "
                f"usually dialout: sudo usermod -aG dialout $USER)")
    return "ok"
