"""Child processes that announce readiness with a line on stdout (nac-sitl, nac-onboard agent), and children that
die with their parent.

start() waits, with a timeout, for the line; stop() sends the child's stop signal and kills it if it does not exit
in time. Its output keeps being read after the ready line (into .output), so a chatty child never blocks on a full
pipe; stderr goes to a temporary file whose text is quoted when the child fails to start.

Every child started here gets a parent-death signal (Linux prctl PR_SET_PDEATHSIG, SIGKILL): a parent killed with
SIGKILL, which runs no clean-up, takes its children with it instead of leaving them running as orphans
(`die_with_parent_preexec` for any other subprocess.Popen).
"""

from __future__ import annotations

import ctypes
import os
import selectors
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

from nac_onboard.errors import OperationFailed

PR_SET_PDEATHSIG = 1  # prctl(2)


class ChildStartError(OperationFailed):
    pass


def _prctl():
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # not Linux: the parent's own clean-up has to do
        return None


def proc_stat(pid: int) -> list[str]:
    """/proc/PID/stat's fields after the command's name (state, ppid, ...); OSError if there is no such process."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def process_running(pid: int) -> bool:
    """Whether process pid runs (a zombie does not: a process that is not our child may be reaped late)."""
    try:
        return proc_stat(pid)[0] != "Z"
    except (OSError, IndexError):
        return False


def die_with_parent(signum: int = signal.SIGKILL) -> None:
    """This process gets signum (SIGKILL: it is killed) when the thread that started it ends: the parent's death,
    SIGKILL included. Called by a process itself (MPI ranks, whose launcher's proxy starts them in sessions of
    their own)."""
    prctl = _prctl()
    if prctl is not None:
        prctl(PR_SET_PDEATHSIG, signum)


def die_with_parent_preexec(signum: int = signal.SIGKILL) -> Callable[[], None] | None:
    """A preexec_fn for subprocess.Popen that gives the child the parent-death signal (SIGTERM for a child whose own
    clean-up matters: mpiexec's, which ends its proxies so that they remove their files). prctl is looked up here, in
    the parent: between fork and exec the child only calls it (no import, no library loading, so other threads'
    locks cannot deadlock it), then exits if the parent already died before the signal was set. The signal
    survives exec (`ip netns exec`, mpiexec, iperf3 keep it) and is sent when the *thread* that started the child
    ends, so start long-lived children from the main thread or a thread that lives as long as they do."""
    prctl = _prctl()
    if prctl is None:
        return None
    parent = os.getpid()

    def preexec() -> None:
        prctl(PR_SET_PDEATHSIG, signum)
        if os.getppid() != parent:
            os._exit(1)

    return preexec


class ReadyProcess:
    def __init__(self, command: list[str], ready_prefix: str, name: str, ready_timeout_s: float = 20.0,
                 stop_signal: int = signal.SIGTERM, env: dict | None = None):
        self.command, self.ready_prefix, self.name = command, ready_prefix.encode(), name
        self.ready_timeout_s, self.stop_signal, self.env = ready_timeout_s, stop_signal, env
        self.proc: subprocess.Popen | None = None
        self.output: deque[str] = deque(maxlen=1000)  # stdout lines, the ready line and what came after
        self._stderr = None
        self._reader: threading.Thread | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def start(self):
        return self.launch().wait_ready()

    def launch(self):
        """Start the process without waiting for it: several start at once, then wait_ready on each."""
        self._stderr = tempfile.TemporaryFile()  # noqa: SIM115 (kept open for the child's whole life)
        self.proc = subprocess.Popen(self.command, stdout=subprocess.PIPE, stderr=self._stderr, env=self.env,
                                     preexec_fn=die_with_parent_preexec())
        return self

    def wait_ready(self):
        """Until the ready line (ChildStartError, with its stderr, if it does not come within ready_timeout_s)."""
        fd = self.proc.stdout.fileno()  # raw reads: a buffered readline would hide lines from select()
        deadline = time.monotonic() + self.ready_timeout_s
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
                self.output.extend(line.decode(errors="replace") for line in lines)
                if any(line.startswith(self.ready_prefix) for line in lines):
                    self._reader = threading.Thread(target=self._drain, args=(fd,), daemon=True)
                    self._reader.start()
                    return self
        self._end(timeout_s=5.0)
        raise ChildStartError(f"{self.name} did not become ready within {self.ready_timeout_s:g} s"
                              f" (exit code {self.proc.returncode}): {self.stderr_text().strip()[-2000:]}")

    def _drain(self, fd: int) -> None:
        pending = b""
        while chunk := os.read(fd, 65536):
            *lines, pending = (pending + chunk).split(b"\n")
            self.output.extend(line.decode(errors="replace") for line in lines)

    def stderr_text(self) -> str:
        if self._stderr is None or self._stderr.closed:
            return ""
        self._stderr.seek(0)
        return self._stderr.read().decode(errors="replace")

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout_s: float = 10.0) -> int:
        """The stop signal, then SIGKILL if it has not exited within timeout_s; returns the exit code."""
        return self._end(timeout_s)

    def signal_stop(self) -> None:
        """The stop signal without waiting: several stop at once, then stop() on each."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(self.stop_signal)

    def kill(self) -> int:
        self.proc.kill()
        return self._end()

    def _end(self, timeout_s: float = 10.0) -> int:
        proc = self.proc
        if proc is None:
            return 0
        if proc.poll() is None:
            proc.send_signal(self.stop_signal)
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout_s)
        if self._reader is not None:
            self._reader.join(timeout=2.0)
        if proc.stdout:
            proc.stdout.close()
        return proc.returncode

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
        if self._stderr is not None:
            self._stderr.close()


class AgentProcess(ReadyProcess):
    """`nac-onboard agent --config FILE` as a child process (the experiment runner and the tests)."""

    def __init__(self, config_path, extra_args: list[str] | None = None, env: dict | None = None,
                 ready_timeout_s: float = 20.0, prefix: list[str] | None = None):
        # prefix: what runs it elsewhere (`ip netns exec NS`: it execs, so the agent gets the signals itself)
        command = [*(prefix or []), sys.executable, "-m", "nac_onboard.cli", "agent", "--config", str(config_path),
                   *(extra_args or [])]
        super().__init__(command, "nac-onboard agent", f"agent ({config_path})", ready_timeout_s,
                         signal.SIGTERM, env)
