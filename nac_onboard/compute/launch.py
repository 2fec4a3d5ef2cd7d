"""The `mpiexec` command of a job: one hydra proxy per companion, started through a launcher called like ssh.

On the fleet each vehicle's companion is a host of its own, so each rank has a proxy of its own. That matters
beyond realism: a hydra proxy whose child dies of a signal SIGKILLs every rank it started, whatever
`-disable-auto-cleanup` says, so ranks that share a proxy die with the first one killed. With a proxy per rank
(the launcher runs it here, or in the vehicle's network namespace) and `-disable-auto-cleanup`, a killed worker
takes nothing else with it and the master trains on with the workers it has left.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import sys
from collections.abc import Iterable
from pathlib import Path

from nac_onboard.errors import BadInput

HOST_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")  # a vehicle id or a namespace: safe in the launcher
# What an MPICH job leaves behind when its processes are killed, each file kept open by its owner while it runs:
# hydra_pmi_proxy's topology of its node for the ranks (the path compiled into the mpich wheel's proxy; TMPDIR is
# not read), removed at the proxy's exit (five per run of the lost-companion tests, 2026-11-28); and each rank's
# shared-memory segment, 1-2 MB of RAM, removed when the job ends well (4,434 of them, 4.5 GB of /dev/shm, after
# two days of this machine's tests and runs, 2026-11-28)
HYDRA_TOPOLOGY_PREFIX = "/tmp/hydra_hwloc_xmlfile_"
MPICH_SHM_PREFIX = "/dev/shm/mpich_shm_"
MPI_SCRATCH = re.compile(re.escape(HYDRA_TOPOLOGY_PREFIX) + r"[A-Za-z0-9]{6}|" + re.escape(MPICH_SHM_PREFIX)
                         + r"[0-9a-f]+_[0-9]+")


def mpiexec_path() -> str:
    """The `mpiexec` installed beside this Python (the mpich wheel), else the one on PATH."""
    mpiexec = Path(sys.executable).parent / "mpiexec"
    return str(mpiexec if mpiexec.exists() else "mpiexec")


def mpi_scratch_files(pids: Iterable[int]) -> list[str]:
    """The MPI scratch files (MPI_SCRATCH: the proxies' topology files, the ranks' shared-memory segments) these
    processes hold open, read from /proc: none for a process gone or not ours to read."""
    found = []
    for pid in pids:
        with contextlib.suppress(OSError):
            for fd in os.listdir(f"/proc/{pid}/fd"):
                with contextlib.suppress(OSError):
                    target = os.readlink(f"/proc/{pid}/fd/{fd}")
                    if MPI_SCRATCH.fullmatch(target):
                        found.append(target)
    return found


def job_processes(mpiexec_args: Iterable) -> list[int]:
    """The hydra proxies on this machine of an `mpiexec` started through a launcher (its -bootstrap-exec: their
    command lines name it), and their children, the ranks. None for another mpiexec."""
    args = [str(a) for a in mpiexec_args]
    if "-bootstrap-exec" not in args[:-1]:
        return []
    launcher = args[args.index("-bootstrap-exec") + 1].encode()
    proxies, parent = [], {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError, ValueError, IndexError):
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    argv = f.read().split(b"\0")
                if argv[0].endswith(b"hydra_pmi_proxy") and launcher in argv:
                    proxies.append(int(entry))
                with open(f"/proc/{entry}/stat", "rb") as f:
                    parent[int(entry)] = int(f.read().rsplit(b")", 1)[1].split()[1])
    return proxies + [pid for pid, ppid in parent.items() if ppid in proxies]


def remove_files(paths: Iterable[str]) -> None:
    for path in paths:
        with contextlib.suppress(OSError):
            os.unlink(path)


def kill_leaving_nothing(pids: Iterable[int]) -> None:
    """SIGKILL each process, then remove the MPI scratch files they held, which a process killed so cannot."""
    pids = list(pids)
    files = mpi_scratch_files(pids)
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    remove_files(files)


def core_binding(ranks: int, cores: int | None = None) -> str:
    """The `mpiexec -bind-to` value for ranks on one machine: one core per rank when there are enough; otherwise
    the master alone on core 0 and the workers shared over the others. A master sharing its core with a worker
    costs twice its own time per iteration, since the waiting rank polls MPI on that core while the other works."""
    cores = cores or len(os.sched_getaffinity(0))
    if cores < 2 or ranks <= cores:
        return "core"
    return "user:" + ",".join(["0"] + [str(1 + k % (cores - 1)) for k in range(ranks - 1)])


def cpu_per_host(hosts: list[str], cores: int | None = None) -> dict[str, int]:
    """The core each host's rank is pinned to, as core_binding places ranks; none on a single core."""
    cores = cores or len(os.sched_getaffinity(0))
    if cores < 2:
        return {}
    binding = core_binding(len(hosts), cores)
    if binding == "core":
        return {host: k for k, host in enumerate(hosts)}
    return {host: int(c) for host, c in zip(hosts, binding.removeprefix("user:").split(","), strict=True)}


def write_launcher(path: Path, cpus: dict[str, int], netns: bool, down_dir: Path | None = None) -> Path:
    """The program hydra calls like ssh (`LAUNCHER [-x] HOST COMMAND...`) to start a host's proxy: here, or
    inside the network namespace named HOST; pinned to the host's core when `cpus` gives one. down_dir (SITL): a
    file named HOST there is a companion that is lost, which the launcher cannot reach (exit 255, as ssh)."""
    cases = "".join(f"  {name}) cpu={cpu} ;;\n" for name, cpu in cpus.items())
    enter = 'ip netns exec "$host" ' if netns else ""
    down = (f'if [ -e "{down_dir}/$host" ]; then echo "launcher: $host: no route to host (lost)" >&2; exit 255; fi\n'
            if down_dir else "")
    path.write_text("#!/bin/sh\n# written by nac-onboard: hydra's bootstrap onto a companion\n"
                    "[ \"$1\" = \"-x\" ] && shift\nhost=$1; shift\n" + down + "cpu=\ncase \"$host\" in\n" + cases +
                    "esac\nif [ -n \"$cpu\" ] && command -v taskset >/dev/null; then\n"
                    f"  exec {enter}taskset -c \"$cpu\" sh -c \"$*\"\nfi\n"
                    f"exec {enter}sh -c \"$*\"\n")
    path.chmod(0o755)
    return path


def mpiexec_command(hosts: list[str], config_dir: Path, server_address: str = "127.0.0.1", netns: bool = False,
                    env: dict[str, str] | None = None, down_dir: Path | None = None) -> list[str]:
    """`mpiexec` up to the program: rank k on hosts[k] (rank 0, the master, first), one proxy each, pinned as
    cpu_per_host says. Writes the launcher and the hostfile (what a lab writes for its Jetsons) to config_dir."""
    for host in hosts:
        if not HOST_NAME.fullmatch(host):
            raise BadInput(f"MPI host {host!r}: expected letters, digits, '_', '.', '-' (at most 64)")
    if len(set(hosts)) != len(hosts):
        raise BadInput(f"MPI hosts must differ, got {hosts}")
    config_dir.mkdir(parents=True, exist_ok=True)
    launcher = write_launcher(config_dir / ("netns-launcher" if netns else "launcher"), cpu_per_host(hosts), netns,
                              down_dir)
    hostfile = config_dir / "hostfile"
    hostfile.write_text("".join(f"{host}:1\n" for host in hosts))
    genv = [part for name, value in (env or {}).items() for part in ("-genv", name, value)]
    return [mpiexec_path(), "-disable-auto-cleanup", "-bootstrap-exec", str(launcher), "-f", str(hostfile),
            "-localhost", server_address, "-n", str(len(hosts)), "-ppn", "1", *genv]
