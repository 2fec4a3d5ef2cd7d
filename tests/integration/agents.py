"""Test-side helpers for the onboard agent: configs on free ports, waiting on log records."""

from __future__ import annotations

import secrets
import time
from pathlib import Path

from nac_onboard.flight_log import read_jsonl
from nac_onboard.tomlfile import dumps_toml
from tests.conftest import free_port


def agent_toml(vehicle_id: str, role: str, sysid: int, autopilot_uri: str, log_dir: Path, peer_port: int,
               peer_targets: list[int], **sections) -> str:
    """An agent config; keyword arguments add keys to sections, e.g. throughput={"probe": True}."""
    config = {
        "vehicle": {"id": vehicle_id, "role": role, "sysid": sysid},
        "autopilot": {"uri": autopilot_uri, "link_timeout_s": 1.0, "reconnect_s": 0.5},
        "log": {"dir": str(log_dir), "run_id": "test"},
        "peers": {"listen": f"127.0.0.1:{peer_port}", "send_to": [f"127.0.0.1:{p}" for p in peer_targets],
                  "rate_hz": 4.0, "timeout_s": 1.0, "key_file": str(fleet_key(log_dir))},
        "state_feed": {"listen": f"127.0.0.1:{free_port()}"},
        "throughput": {"bind": "127.0.0.1", "port": free_port()},
    }
    for name, values in sections.items():
        config.setdefault(name, {}).update(values)
    return dumps_toml(config)


def fleet_key(log_dir: Path) -> Path:
    """The test fleet's key, one per log directory, shared by the agents logging there."""
    path = Path(log_dir) / "fleet.key"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(secrets.token_hex(32) + "\n")
    return path


def wait_for_record(path: Path, predicate, timeout_s: float = 10.0) -> dict:
    """The first record of the log at path satisfying predicate, waiting for the agent to write it."""
    deadline = time.monotonic() + timeout_s
    while True:
        if path.exists():
            for record in read_jsonl(path).records:
                if predicate(record):
                    return record
        if time.monotonic() > deadline:
            raise AssertionError(f"no matching record in {path} within {timeout_s:g} s")
        time.sleep(0.05)


def kind(name: str, **fields):
    return lambda r: r["kind"] == name and all(r.get(k) == v for k, v in fields.items())
