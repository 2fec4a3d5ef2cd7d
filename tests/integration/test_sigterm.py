"""SIGTERM (`kill`, `timeout`, systemd's stop) stops every long-running command as Ctrl-C does: its clean-up runs
and it exits on its own (issue 34: `nac-sitl experiment` once ran on to "completed"; the experiment's own tests are
in test_experiment.py and test_kernel_network.py, the agent's in test_agent.py)."""

import signal
import socket
import sys
from pathlib import Path

import pytest

from nac_onboard.child_process import ReadyProcess
from tests.conftest import allocate_base_port, free_port

GOLDEN_RUN = Path(__file__).parents[1] / "data" / "golden-run"
BIN = Path(sys.executable).parent


def sitl_run() -> tuple[list[str], str, str]:
    base = allocate_base_port(1)
    return ([str(BIN / "nac-sitl"), "run", "--vehicles", "1", "--speedup", "5", "--gcs-base-port", str(base),
             "--companion-base-port", str(base + 1), "--tcp-base-port", "0"], "nac-sitl ready", "nac-sitl stopped")


def view() -> tuple[list[str], str, str]:
    return [str(BIN / "nac-ground"), "view", str(GOLDEN_RUN), "--address", f"127.0.0.1:{free_port()}"], "view:", ""


def throughput_server() -> tuple[list[str], str, str]:
    return ([str(BIN / "nac-onboard"), "throughput", "server", "--bind", "127.0.0.1", "--port", "0"],
            "throughput server listening", "")


@pytest.mark.parametrize("command", [sitl_run, view, throughput_server], ids=lambda c: c.__name__)
def test_sigterm_stops_a_long_running_command_cleanly(command):
    argv, ready, farewell = command()
    proc = ReadyProcess(argv, ready, argv[1], ready_timeout_s=30.0, stop_signal=signal.SIGTERM).start()
    try:
        listening = [line for line in proc.output if line.startswith(ready)]
        code = proc.stop(timeout_s=10.0)  # SIGTERM, then SIGKILL (exit -9) if it has not ended within 10 s
        assert code == 0, f"exit {code}: {proc.stderr_text()[-1000:]}"
        assert "Traceback" not in proc.stderr_text()
        assert farewell in "\n".join(proc.output)
        if command is view:  # the server is closed, not left behind
            host, port = argv[-1].rsplit(":", 1)
            with socket.socket() as s, pytest.raises(ConnectionRefusedError):
                s.connect((host, int(port)))
        assert listening
    finally:
        proc.stop(timeout_s=1.0)
