"""The run's one clock: the simulator's measured pace, and readers that never go back in time."""

import pytest

from nac_onboard import clock


def test_pace_is_measured_from_the_simulators_progress_and_starts_nominal():
    pace = clock.Pace(nominal=4.0, window_s=1.0)
    assert pace.add(0.0, mono_s=100.0) == 4.0, "nothing measured yet"
    for k in range(1, 11):  # a simulator that manages 2.5 simulated seconds per wall second
        value = pace.add(2.5 * 0.2 * k, mono_s=100.0 + 0.2 * k)
    assert value == pytest.approx(2.5)
    assert pace.add(100.0, mono_s=102.2) == pytest.approx(5.0), "a catch-up burst is capped at 1.25x nominal"


def test_a_reader_never_goes_back_when_the_published_clock_lags(tmp_path, monkeypatch):
    path = tmp_path / "clock.json"
    now = {"mono": 50.0}
    monkeypatch.setattr(clock.time, "monotonic", lambda: now["mono"])
    clock.publish(str(path), 4.0, 10.0)
    reader = clock.SharedClock(str(path))
    now["mono"] = 51.0
    ahead = reader.now_s()
    assert ahead == pytest.approx(14.0), "extrapolated at the published pace"
    clock.publish(str(path), 2.0, 12.0)  # the simulator was slower than its pace: its clock is behind
    now["mono"] = 51.6
    later = reader.now_s()
    assert later >= ahead and reader.speedup == 2.0
    now["mono"] = 54.0
    assert reader.now_s() == pytest.approx(12.0 + 3.0 * 2.0)
