import os
import random
import socket
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")
REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


def _free(port: int, kind: int) -> bool:
    with socket.socket(socket.AF_INET, kind) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def allocate_base_port(vehicles: int, step: int = 10, slots: int = 2) -> int:
    """A base port B with B+step*i+k free (UDP and TCP) for every vehicle i and slot k < slots (ground, companion,
    ...)."""
    for _ in range(200):
        base = random.randrange(20000, 60000 - step * vehicles, 2)
        ports = [base + step * i + k for i in range(vehicles) for k in range(slots)]
        if all(_free(p, socket.SOCK_DGRAM) and _free(p, socket.SOCK_STREAM) for p in ports):
            return base
    raise RuntimeError("no free port range found")


@pytest.fixture
def base_port():
    return allocate_base_port


def free_port() -> int:
    """A port free for both UDP and TCP on loopback right now."""
    for _ in range(200):
        port = random.randrange(20000, 60000)
        if _free(port, socket.SOCK_DGRAM) and _free(port, socket.SOCK_STREAM):
            return port
    raise RuntimeError("no free port found")
