import os
from pathlib import Path

import pytest

os.environ.setdefault("MAVLINK20", "1")  # before anything below imports pymavlink
os.environ.setdefault("NAC_RECORDS_STRICT", "1")  # a record that strays from nac_onboard/records/kinds.py fails

from sitl.launcher import allocate_base_port, free_port  # noqa: E402

__all__ = ["allocate_base_port", "free_port"]  # many tests do `from tests.conftest import free_port`

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / "shared" / "data"


@pytest.fixture(autouse=True)
def shared_data_dir(monkeypatch):
    """Every test finds the Forest Fires CSV in ../shared/data (the project commits no copy), whatever ran before
    it; a test about missing data sets its own NAC_DATA_DIR. A module-scoped fixture runs before this one and
    sets it itself."""
    monkeypatch.setenv("NAC_DATA_DIR", str(SHARED_DATA))


@pytest.fixture
def base_port():
    return allocate_base_port
