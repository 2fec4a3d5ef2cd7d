"""Test-side helper: a child's console read line by line in the background, with an event for the line a test
waits for (a CLI run whose progress is only visible there)."""

from __future__ import annotations

import re
import subprocess
import threading


class Console:
    def __init__(self, proc: subprocess.Popen, pattern: str):
        self.lines: list[str] = []
        self.seen = threading.Event()
        self._pattern = re.compile(pattern)
        self._reader = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._reader.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            self.lines.append(line)
            if self._pattern.search(line):
                self.seen.set()

    def text(self) -> str:
        return "".join(self.lines)

    def join(self, timeout_s: float = 2.0) -> None:
        self._reader.join(timeout_s)


def as_at_a_terminal() -> None:
    """preexec_fn for a child a test will Ctrl-C: SIGINT back to its default, as in a terminal's foreground job (a
    suite started in the background by a non-interactive shell has SIGINT ignored, and Python keeps it so)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_DFL)
