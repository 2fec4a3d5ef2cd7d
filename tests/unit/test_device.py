"""Device profiles: a bad one is refused naming its file, field and range; a stretched segment lasts the device's
time on the run's clock (a lower bound the hold guarantees, not a measured speed); `nac-onboard bench` prints it."""

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from nac_onboard.clock import Clock
from nac_onboard.compute import cpu_score
from nac_onboard.compute.device import HOST, CpuStretch, load_device_profile, shipped_devices
from nac_onboard.errors import BadInput, OperationFailed
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


HOST_SCORE = 2914.0  # this project's machine, `nac-onboard cpu-score` on 2026-11-27 (tests/data/7z-b-mmt1.txt)


@pytest.fixture
def host_score(monkeypatch, tmp_path):
    """A known host score, and a cache of its own: no test measures the host or reads the user's cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv(cpu_score.HOST_CPU_SCORE_ENV, str(HOST_SCORE))


def test_the_shipped_jetson_profiles_are_the_hosts_score_over_their_published_one(host_score):
    assert shipped_devices() == ["jetson-orin-nano", "jetson-orin-nx", "jetson-tx2", "jetson-xavier-nx"]
    published = {"jetson-tx2": 1977, "jetson-xavier-nx": 2201, "jetson-orin-nano": 2153, "jetson-orin-nx": 2379}
    for name, score in published.items():
        device = load_device_profile(name)  # a shipped profile by its name
        assert device.name == name and device.cpu_score_mips == score
        assert device.slowdown == pytest.approx(HOST_SCORE / score)
        assert "sbc-bench" in device.source and f"7-zip single {score}" in device.source


def test_a_device_faster_than_the_host_is_not_stretched(monkeypatch, tmp_path):
    monkeypatch.setenv(cpu_score.HOST_CPU_SCORE_ENV, "1500")
    assert load_device_profile("jetson-orin-nx").slowdown == 1.0


def test_without_a_host_score_the_profile_names_the_command_that_measures_it(monkeypatch, tmp_path):
    monkeypatch.delenv(cpu_score.HOST_CPU_SCORE_ENV, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    with pytest.raises(BadInput, match="run `nac-onboard cpu-score` once"):
        load_device_profile("jetson-tx2")
    cache = tmp_path / "cache" / "nac" / "host-cpu-score.json"
    cache.parent.mkdir(parents=True)
    cache.write_text(json.dumps({"cpu": "another CPU", "build": "7-Zip", "score_mips": 3000.0}))
    with pytest.raises(BadInput, match="not measured yet"):
        load_device_profile("jetson-tx2")  # measured on another CPU: not this host's
    cache.write_text("{damaged")
    with pytest.raises(BadInput, match="not measured yet"):
        load_device_profile("jetson-tx2")
    cache.write_text(json.dumps({"cpu": cpu_score._cpu_model(), "build": "7-Zip", "score_mips": 3954.0}))
    assert load_device_profile("jetson-tx2").slowdown == pytest.approx(2.0)
    monkeypatch.setenv(cpu_score.HOST_CPU_SCORE_ENV, "fast")
    with pytest.raises(BadInput, match=r"\$NAC_HOST_CPU_SCORE: expected 7-Zip's single-thread rating"):
        load_device_profile("jetson-tx2")


@pytest.mark.parametrize("body, message", [
    ('[device]\nname = "a"\nslowdown = 2\ncpu_score_mips = 2000\nsource = "s"\n', "exactly one of slowdown"),
    ('[device]\nname = "a"\nsource = "s"\n', "exactly one of slowdown"),
    ('[device]\nname = "a"\ncpu_score_mips = 5\nsource = "s"\n', "cpu_score_mips: expected a number in 100..100000"),
])
def test_a_score_profile_is_checked_as_a_slowdown_one_is(tmp_path, host_score, body, message):
    path = profile(tmp_path, body)
    with pytest.raises(BadInput, match=re.escape(message)) as err:
        load_device_profile(path)
    assert str(path) in str(err.value)


def test_the_rating_is_read_from_7zips_own_benchmark_output():
    """The output of `7z b -mmt1` on this project's machine: the rating is the Tot line's last figure."""
    assert cpu_score.parse_rating((Path(__file__).parents[1] / "data" / "7z-b-mmt1.txt").read_text()) == HOST_SCORE
    with pytest.raises(OperationFailed, match="no 'Tot:' line"):
        cpu_score.parse_rating("7-Zip [64] 26.02\nRAM size: 7765 MB\n")
