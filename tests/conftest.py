import os
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")  # before anything below imports pymavlink

from sitl.launcher import allocate_base_port, free_port  # noqa: E402

__all__ = ["allocate_base_port", "free_port"]  # many tests do `from tests.conftest import free_port`

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture
def base_port():
    return allocate_base_port
