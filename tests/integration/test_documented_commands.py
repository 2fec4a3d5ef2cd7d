"""Every command line in README.md and docs/*.md, run as written (issue 33): a SITL flight, a short experiment with
its analysis, comparison, calibration and view, the onboard agents on a SITL. Each runs in a network namespace of
its own, so the documented ports (14550, 14551, 47200...) are free whatever else runs on this host, and in a scratch
folder holding what the docs assume is beside you (the checkout's `.venv`, `missions/`, `deploy/`; placeholders
such as `runs/static` or `RUN` linked to the short run). A documented line that this test neither runs nor
excuses, with the reason, fails it: so none can rot unnoticed."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import time
import uuid
from pathlib import Path

import pytest

from nac_onboard.child_process import die_with_parent_preexec
from sitl.network.netns import delete_namespace
from tests.conftest import SHARED_DATA
from tests.integration.test_experiment import write_scenario

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BLOCK = re.compile(r"```(?:sh|bash)\n(.*?)```", re.S)

NOT_RUN = {
    "make demo": "two 130 s flights at 4x, 1.5 minutes; `make test` is CI's own command",
    "make test": "the suite this test is part of",
    "nac-sitl experiment paper-flight-moving": "a 130 s flight at 4x, as make demo runs it; test_kernel_network "
                                               "flies it on the htb air",
    "nac-sitl experiment paper-flight-moving --links replay:runs/flight-X":
        "a 130 s flight at 4x; replay is test_experiment's test_a_recorded_run_replays_its_links_on_the_kernel_network",
    "nac-sitl experiment paper-sim-moving --speedup 4 --view":
        "15 s of a 60 s scenario; `--view` live is test_view's test_the_live_page_follows_the_simulator_...",
    "nac-ground view /var/log/nac/RUN --follow": "a companion's log folder; --follow is test_view's 200 MB record test",
    "nac-ground view --live --connect udpin:0.0.0.0:14550 --feed 192.168.1.10:47200":
        "real vehicles at their addresses; --live against a SITL is test_view_live",
    "nac-onboard throughput probe 192.168.1.11 -t 2": "another companion's address; the probe is test_throughput's",
    "nac-onboard data fetch": "needs the internet; the data is in ../shared/data (test_ground_cli checks offline)",
    "sudo deploy/install.sh --role worker --id uav2 --fleet-key fleet.key":
        "installs into /; test_deploy runs install.sh with the same options into a scratch root",
    "nac-onboard log check /var/log/nac/<run>/master/*.jsonl": "run on the master's logs in the agents' log folder",
    "mpiexec -n 3 -bind-to user:0,1,1 python -m mpi4py -m nac_onboard.compute --task linreg --duration-s 200 "
    "--emulate sleep --channel wifi-flight --positions feed --vehicles master,worker1,worker2 --out runs/lr":
        "200 s, and agents named master, worker1, worker2 feeding positions; test_compute runs it for 2 s",
    ".venv/bin/nac-sitl run --vehicles 3 &": "run as docs/sitl.md's `--speedup 5` line, the same SITL 5x faster",
}


def documented() -> dict[str, str]:
    """Each command line of a ```sh block (continuations joined, trailing comments dropped) -> where it is."""
    found = {}
    for path in DOCS:
        for block in BLOCK.findall(path.read_text()):
            for line in block.replace("\\\n", " ").splitlines():
                command = re.sub(r"\s+#\s.*$", "", line).strip()
                command = re.sub(r"\s+", " ", command)
                if command and not command.startswith("#"):
                    found.setdefault(command, path.name)
    return found


class Shell:
    """Commands as a user types them, in a scratch folder and a network namespace of their own."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.ns = f"nacdoc-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self.ran: set[str] = set()
        self.background: list[subprocess.Popen] = []
        subprocess.run(["ip", "netns", "add", self.ns], check=True, timeout=10)
        subprocess.run(["ip", "-n", self.ns, "link", "set", "lo", "up"], check=True, timeout=10)
        for name in (".venv", "missions", "deploy"):
            (folder / name).symlink_to(ROOT / name)
        self.env = dict(os.environ, PATH=f"{ROOT / '.venv' / 'bin'}:{os.environ['PATH']}",
                        NAC_DATA_DIR=str(SHARED_DATA))

    def _argv(self, command: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns, "bash", "-c", command]

    def run(self, command: str, timeout_s: float = 120.0, expect: int = 0) -> str:
        self.ran.add(command)
        done = subprocess.run(self._argv(command), cwd=self.folder, env=self.env, capture_output=True, text=True,
                              timeout=timeout_s)
        assert done.returncode == expect, f"{command!r} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
        return done.stdout + done.stderr

    def start(self, command: str, ready: str, timeout_s: float = 30.0) -> subprocess.Popen:
        """A line documented with `&` (or one that serves until stopped), running once it prints `ready`."""
        self.ran.add(command)
        proc = subprocess.Popen(self._argv(command.removesuffix("&").strip()), cwd=self.folder, env=self.env,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
                                preexec_fn=die_with_parent_preexec())
        self.background.append(proc)
        deadline = time.monotonic() + timeout_s
        seen = []
        while time.monotonic() < deadline:  # readline returns at the child's exit too
            line = proc.stdout.readline()
            seen.append(line)
            if ready in line:
                return proc
            if not line and proc.poll() is not None:
                break
        raise AssertionError(f"{command!r} never printed {ready!r}: {''.join(seen)}")

    def stop(self, proc: subprocess.Popen) -> None:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5)
        proc.stdout.close()

    def close(self) -> None:
        for proc in self.background:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait(5)
            proc.stdout.close()
        delete_namespace(self.ns)


@pytest.fixture
def shell(tmp_path):
    if os.geteuid() != 0 or not shutil.which("ip"):
        pytest.skip("runs the documented ports in a network namespace of its own: needs root and ip")
    made = Shell(tmp_path)
    yield made
    made.close()


def fly_the_readme_and_files_examples(sh: Shell) -> None:
    sitl = sh.start(".venv/bin/nac-sitl run --vehicles 3 --speedup 5", "14550")
    sh.run(".venv/bin/nac-ground mission upload missions/examples/paper-sim-master.plan")
    sh.run(".venv/bin/nac-ground arm")
    sh.run(".venv/bin/nac-ground mission start")
    sh.run(".venv/bin/nac-ground wait mission-complete --timeout-s 300")
    status = sh.run(".venv/bin/nac-ground --connect udpin:0.0.0.0:14550 --connect udpin:0.0.0.0:14560 status")
    rows = {line.split()[0]: line.split() for line in status.splitlines()[1:] if line.strip()}
    assert set(rows) == {"1", "2"} and rows["1"][-2] == "3/3", f"vehicle 1 flew its 3 items, 2 heard: {status}"
    shutil.copy(ROOT / "missions" / "examples" / "paper-sim-master.plan", sh.folder / "plan.plan")
    assert "valid" in sh.run("nac-ground mission validate missions/examples/paper-sim-master.plan")
    sh.run("nac-ground mission convert plan.plan plan.waypoints")
    assert (sh.folder / "plan.waypoints").read_text().startswith("QGC WPL 110")
    sh.stop(sitl)  # docs/files.md's flight, on a vehicle fresh from boot as README's was
    # at 2x, not 5x: its `arm` and `mission start` are two programs, and ArduCopter disarms a copter left on the
    # ground for DISARM_DELAY (10 s): at 5x that is 2 s of wall time, which a loaded CI machine twice took to start
    # the second (the copter said "Mission start refused: arm first"); at 2x it is 5 s
    sitl = sh.start(".venv/bin/nac-sitl run --vehicles 3 --speedup 2", "14550")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 mission upload missions/examples/paper-sim-master.plan")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 arm")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 mission start")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 wait mission-complete --timeout-s 300")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 wait landed --timeout-s 120")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 --connect udpin:0.0.0.0:14560 status")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 mode STABILIZE")
    sh.run("nac-ground --connect udpin:0.0.0.0:14550 arm")  # flies again, as the comment says
    sh.stop(sitl)


def run_and_read_an_experiment(sh: Shell) -> None:
    scenario = write_scenario(sh.folder, duration_s=14.0)  # w1 from 5 m to 33 m: calibrate needs the spread (8 s: not)
    scenario.rename(sh.folder / "my.toml")
    sh.run("nac-sitl experiment my.toml --speedup 4 --out runs/try1", timeout_s=180)
    assert (sh.folder / "runs" / "try1" / "report.md").exists()
    sh.run("nac-ground logs analyze runs/try1")
    for alias in ("static", "moving", "range-sweep-X", "paper-sim-moving-X"):
        (sh.folder / "runs" / alias).symlink_to("try1")
    (sh.folder / "RUN").symlink_to("runs/try1")
    sh.run("nac-ground logs compare runs/static runs/moving --out runs/cmp")
    assert (sh.folder / "runs" / "cmp" / "report.md").exists()
    sh.run("nac-ground logs calibrate runs/range-sweep-X --out my-wifi.toml")
    assert "median range" in sh.run("nac-sitl radio my-wifi.toml --draws 500")
    assert "median range" in sh.run("nac-sitl radio wifi-flight")
    sh.run("nac-ground view RUN --screenshot view.png", timeout_s=60)
    assert (sh.folder / "view.png").read_bytes()[:4] == b"\x89PNG"
    sh.stop(sh.start("nac-ground view runs/paper-sim-moving-X", "view: http://"))
    sh.run("mpiexec -n 4 -bind-to user:0,1,1,1 python -m mpi4py -m nac_onboard.compute --task matmul --iterations 40 "
           "--out runs/mm", timeout_s=120)
    assert "--task" in sh.run("nac-onboard compute --help")


def run_the_onboard_agents(sh: Shell) -> None:
    sh.run("cp deploy/master.toml deploy/worker.toml .")
    sh.run('python3 -c "import secrets; print(secrets.token_hex(32))" > fleet.key; chmod 600 fleet.key')
    one_machine = {
        "master": {"autopilot.uri": "udpin:127.0.0.1:14551", "log.dir": "logs", "peers.listen": "127.0.0.1:47100",
                   "peers.send_to": ["127.0.0.1:47101"], "throughput.port": 5202},
        "worker": {"autopilot.uri": "udpin:127.0.0.1:14561", "log.dir": "logs", "peers.listen": "127.0.0.1:47101",
                   "peers.send_to": ["127.0.0.1:47100"], "state_feed.listen": "127.0.0.1:47201"}}
    for name, edits in one_machine.items():  # docs/agent.md's paragraph below the commands, key by key
        config = sh.folder / f"{name}.toml"
        config.write_text(edit_toml(config.read_text(), edits))
    sitl = sh.start("nac-sitl run --vehicles 2 &", "nac-sitl ready")
    agents = [sh.start(f"nac-onboard agent --config {name}.toml", "ready") for name in ("master", "worker")]
    deadline = time.monotonic() + 30.0
    while True:  # the worker is heard once its peer state has arrived (2 a second)
        state = json.loads(sh.run("nac-onboard state"))
        if "worker1" in state["peers"] or time.monotonic() > deadline:
            break
        time.sleep(0.2)
    assert state["self"]["id"] == "master" and not state["peers"]["worker1"]["lost"], state
    sh.run("nac-onboard doctor --config master.toml")
    sh.run("nac-onboard mpi hostfile --out hostfile")
    sh.run("nac-onboard mpi run -- python -m mpi4py -m nac_onboard.compute --task matmul", timeout_s=120)
    for agent in agents:
        sh.stop(agent)
    logs = sorted((sh.folder / "logs").glob("*/master/*.jsonl"))
    assert logs, "the master's logs"
    sh.run(f"nac-onboard log check {' '.join(str(p.relative_to(sh.folder)) for p in logs)}")
    sh.stop(sh.start("nac-onboard throughput server", "5201"))
    sh.stop(sitl)


def edit_toml(text: str, edits: dict) -> str:
    """Each "section.key" set: the first `key = ...` line after `[section]` replaced."""
    for key, value in edits.items():
        section, name = key.split(".")
        start = text.index(f"[{section}]")
        line = re.compile(rf"^{name} = .*$", re.M).search(text, start)
        text = text[:line.start()] + f"{name} = {json.dumps(value)}" + text[line.end():]
    return text


@pytest.mark.slow
def test_every_documented_command_runs_as_written(shell):
    """README and docs, top to bottom: each command line runs here as written and exits 0, or is named in NOT_RUN
    with the test that covers it; and NOT_RUN names no line the docs no longer have."""
    commands = documented()
    stale = set(NOT_RUN) - set(commands)
    assert not stale, f"NOT_RUN names lines the docs no longer have: {stale}"
    fly_the_readme_and_files_examples(shell)
    run_and_read_an_experiment(shell)
    run_the_onboard_agents(shell)
    shell.run('python3 -c "import secrets; print(secrets.token_hex(32))" > fleet.key')  # docs/security.md
    assert "slowdown = 0.5 / " in shell.run("nac-onboard bench --task linreg --seconds 1 --device-ms 0.5")
    missing = {c: f for c, f in commands.items() if c not in shell.ran and c not in NOT_RUN}
    assert not missing, f"documented but neither run nor excused: {missing}"
