"""A run's watchdog: the one process of `nac-sitl experiment` that outlives it, just long enough to clean up after it.

SIGKILL runs no clean-up: the runner's direct children die with it (their parent-death signal, child_process.py),
but MPI's proxies and ranks run in sessions of their own and the kernel network's namespaces are files, not
processes. So the runner starts this process first (`Watchdog.start`), hands it the run's token (set in the
environment of every process the run starts, and so of their children, ranks included) and its namespace prefix,
and holds the write end of its stdin. When that pipe closes, however the runner ended, the watchdog kills every
process that carries the token, removes the run's namespaces (with whatever still runs inside) and the MPI scratch
files it was told of (launch.py), then exits. After a clean end it finds nothing left; after SIGKILL it is
the clean-up, within a second.

    python -m sitl.experiment.watchdog    (stdin: `token T`, `netns PREFIX`, `file PATH` lines; EOF: clean up, exit)
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import signal
import subprocess
import sys
from collections.abc import Iterable

from nac_onboard.compute.launch import MPI_SCRATCH, kill_leaving_nothing, remove_files

log = logging.getLogger(__name__)
TOKEN_ENV = "NAC_RUN_TOKEN"
KILL_PASSES = 5  # a process may fork while the previous pass killed its parent: look again until none is found
EXIT_TIMEOUT_S = 10.0


def new_token() -> str:
    return secrets.token_hex(8)


def processes_with(token: str) -> list[int]:
    """Every process whose environment holds TOKEN_ENV=token (the run's processes), this one excepted."""
    marker = f"{TOKEN_ENV}={token}".encode()
    found = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit() or int(entry) == os.getpid():
            continue
        try:
            with open(f"/proc/{entry}/environ", "rb") as f:
                environ = f.read()
        except OSError:  # gone, or not ours to read
            continue
        if marker in environ.split(b"\0"):
            found.append(int(entry))
    return found


def kill_run(token: str) -> list[int]:
    """SIGKILL every process of the run; returns their pids."""
    killed: list[int] = []
    for _ in range(KILL_PASSES):
        pids = processes_with(token)
        if not pids:
            break
        kill_leaving_nothing(pids)
        killed += pids
    return killed


def clean_up(token: str | None, prefixes: list[str], files: Iterable[str] = ()) -> None:
    from sitl.network import netns

    if token:
        kill_run(token)
    for prefix in prefixes:
        for name in netns.namespaces():
            if name.startswith(prefix + "-"):
                netns.delete_namespace(name)
    if token:
        kill_run(token)
    remove_files(files)


def main() -> int:
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # the runner's end is the pipe's end, only
        signal.signal(signum, signal.SIG_IGN)
    token, prefixes, files = None, [], []
    for line in sys.stdin.buffer:
        word, _, value = line.decode(errors="replace").strip().partition(" ")
        if word == "token" and value:
            token = value
        elif word == "netns" and value.startswith("nacnet-"):
            prefixes.append(value)
        elif word == "file" and MPI_SCRATCH.fullmatch(value):  # nothing else is removed on request
            files.append(value)
    clean_up(token, prefixes, files)
    return 0


class Watchdog:
    """The runner's side: start() before any other child, watch_namespaces() before creating them, close() at the
    very end (the watchdog then finds nothing left, and exits)."""

    def __init__(self):
        self.token = new_token()
        self.proc: subprocess.Popen | None = None

    def start(self) -> Watchdog:
        env = {k: v for k, v in os.environ.items() if k != TOKEN_ENV}  # it must not find itself
        # its own session: a Ctrl-C at the terminal or a signal to the runner's group does not reach it
        self.proc = subprocess.Popen([sys.executable, "-m", "sitl.experiment.watchdog"], stdin=subprocess.PIPE,
                                     stdout=subprocess.DEVNULL, env=env, start_new_session=True)
        self._send(f"token {self.token}")
        return self

    @property
    def environ(self) -> dict[str, str]:
        """What to add to the environment of every process of the run."""
        return {TOKEN_ENV: self.token}

    def watch_namespaces(self, prefix: str) -> None:
        self._send(f"netns {prefix}")

    def remove_at_end(self, paths: list[str]) -> None:
        """Files to remove when the run ends, however it ends: the MPI job's scratch files, which its proxies and
        ranks do not remove when mpiexec dies with a SIGKILLed runner (three topology files and three shared-memory
        segments per run of the SIGKILL test, 2026-11-28)."""
        for path in paths:
            self._send(f"file {path}")

    def _send(self, line: str) -> None:
        try:
            self.proc.stdin.write(line.encode() + b"\n")
            self.proc.stdin.flush()
        except (OSError, ValueError) as err:  # it died: the runner's own clean-up has to do
            log.warning("the run's watchdog is gone: %s", err)

    def close(self, timeout_s: float = EXIT_TIMEOUT_S) -> None:
        if self.proc is None:
            return
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("the run's watchdog did not finish its clean-up within %g s", timeout_s)
        self.proc = None


if __name__ == "__main__":
    sys.exit(main())
