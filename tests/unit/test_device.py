"""Device profiles: a bad one is refused naming its file, field and range; a stretched segment lasts the device's
time on the run's clock (a lower bound the hold guarantees, not a measured speed); `nac-onboard bench` prints it."""

import re
import subprocess
import sys
import time

import pytest

from nac_onboard.clock import Clock
from nac_onboard.compute.device import HOST, CpuStretch, load_device_profile
from nac_onboard.errors import BadInput
from tests.conftest import SHARED_DATA


def profile(tmp_path, body: str):
    path = tmp_path / "device.toml"
    path.write_text(body)
    return path


def test_a_profile_gives_its_name_slowdown_and_source(tmp_path):
    device = load_device_profile(profile(tmp_path, '[device]\nname = "tx2"\nslowdown = 6\nsource = "bench, lab X"\n'))
    assert (device.name, device.slowdown, device.source) == ("tx2", 6.0, "bench, lab X")
    assert HOST.slowdown == 1.0


@pytest.mark.parametrize("body, message", [
    ('[device]\nname = "a"\nslowdown = 0.5\nsource = "s"\n', "slowdown: expected a number in 1..1000"),
    ('[device]\nname = "a"\nslowdown = 1e9\nsource = "s"\n', "slowdown: expected a number in 1..1000"),
    ('[device]\nname = "a"\nslowdown = "fast"\nsource = "s"\n', "slowdown: expected a number"),
    ('[device]\nname = "a"\nslowdown = 3\n', "source: expected who measured"),
    ('[device]\nslowdown = 3\nsource = "s"\n', "name: expected a non-empty string"),
    ('[device]\nname = "a"\nslowdown = 3\nsource = "s"\nclock_ghz = 2\n', "unknown fields ['clock_ghz']"),
    ('name = "a"\n', "expected a [device] table"),
    ('[device\n', "not TOML"),
])
def test_a_bad_profile_is_refused_naming_the_file_and_field(tmp_path, body, message):
    path = profile(tmp_path, body)
    with pytest.raises(BadInput, match=re.escape(message)) as err:
        load_device_profile(path)
    assert str(path) in str(err.value) and err.value.exit_code == 2


class _FourTimes(Clock):
    speedup = 4.0


def test_a_segment_is_held_until_the_devices_time_has_passed_on_the_runs_clock():
    """CPU time is this process's own (a loaded host does not change it), and the hold waits at least until
    slowdown x that CPU time has passed in simulated seconds: both hold whatever the machine's load."""
    stretch = CpuStretch(50.0, _FourTimes())
    stretch.begin()
    wall0, cpu0 = time.monotonic(), time.process_time()
    while time.process_time() - cpu0 < 0.01:
        pass
    device_s = stretch.hold()
    assert device_s >= 50 * 0.01
    assert time.monotonic() - wall0 >= device_s / 4 - 1e-3, "held for the device's time at 4x"
    assert stretch.late == 0
    assert not CpuStretch(1.0, Clock()).active


def test_bench_prints_the_jobs_cpu_per_iteration_and_a_slowdown():
    done = subprocess.run([sys.executable, "-m", "nac_onboard.cli", "bench", "--task", "linreg", "--seconds", "0.2",
                           "--data", str(SHARED_DATA / "forestfires.csv"), "--device-ms", "1"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    first, second = done.stdout.splitlines()
    assert first.startswith("linreg, 3 workers: ") and "ms CPU per iteration" in first
    assert second.startswith("slowdown = 1 / ")
