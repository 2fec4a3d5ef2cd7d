"""What the benchmarks share: the `--smoke` flag every one has (the same code path with tiny sizes, so the test
suite runs them all), a process's CPU time and memory from /proc, and a scratch folder for whole runs on the kernel
network."""

from __future__ import annotations

import argparse
import os
import secrets
import sys
import tempfile
from pathlib import Path

from nac_onboard.records import kinds
from nac_onboard.tomlfile import write_toml
from sitl.launcher import free_port
from sitl.network.netns import NetworkUnavailable, check_kernel_network

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def parse_args(parser: argparse.ArgumentParser, smoke_defaults: dict) -> argparse.Namespace:
    """parser's arguments; with --smoke, smoke_defaults replace the defaults (explicit flags still win)."""
    parser.add_argument("--smoke", action="store_true", help=f"tiny run to check the benchmark works: {smoke_defaults}")
    if parser.parse_known_args()[0].smoke:
        parser.set_defaults(**smoke_defaults)
    return parser.parse_args()


def cpu_s(pid: int) -> float:
    """CPU seconds (user + system) the process has used."""
    fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def memory_mb(pid: int) -> dict:
    """VmRSS (now) and VmHWM (peak), MB."""
    status = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines())
    return {key: int(status[key].split()[0]) / 1024 for key in ("VmRSS", "VmHWM")}


def agent_config(folder: Path, vehicle_id: str, role: str, autopilot_uri: str, **sections) -> Path:
    """An agent config on free loopback ports, logging into folder (run id "bench"), with a fleet key beside it;
    keyword arguments add keys to sections, e.g. routing={"endpoints": [...]}."""
    (folder / kinds.FLEET_KEY.name).write_text(secrets.token_hex(32) + "\n")
    config = {
        "vehicle": {"id": vehicle_id, "role": role, "sysid": 1},
        "autopilot": {"uri": autopilot_uri},
        "log": {"dir": str(folder), "run_id": "bench"},
        "peers": {"listen": f"127.0.0.1:{free_port()}", "send_to": [f"127.0.0.1:{free_port()}"],
                  "key_file": kinds.FLEET_KEY.name},
        "state_feed": {"listen": f"127.0.0.1:{free_port()}"},
        "throughput": {"bind": "127.0.0.1", "port": free_port()},
    }
    for name, values in sections.items():
        config.setdefault(name, {}).update(values)
    path = folder / "agent.toml"
    write_toml(path, config)
    return path


def kernel_runs_folder(script: str, prefix: str) -> Path | None:
    """A scratch folder for whole runs on the kernel network, the data directory set for them; None, the reason
    printed, where this machine cannot make network namespaces."""
    try:
        check_kernel_network()
    except NetworkUnavailable as err:
        print(f"{script}: {err}", file=sys.stderr)
        return None
    os.environ.setdefault("NAC_DATA_DIR", str(DATA))
    return Path(tempfile.mkdtemp(prefix=prefix))
