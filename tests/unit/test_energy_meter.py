"""The experiment's energy meter (sitl/experiment/energy_meter.py) on inputs it is given: shares, powers, the
companion pack, and the vehicles whose pack empties."""

import os

import pytest

from nac_onboard.flight_log import JsonlLog, read_jsonl
from sitl.experiment.energy_meter import EnergyMeter, namespace_bytes, process_cpu_s
from sitl.experiment.scenario import EnergyPlan
from sitl.vehicle import energy

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced


def meter(tmp_path, companion_mah=(1300.0, 1300.0), slowdown=1.0, radio_counted=True):
    log = JsonlLog(tmp_path / "energy.jsonl")
    return EnergyMeter(["m", "w"], EnergyPlan(), list(companion_mah), ["zeng-2019", "tarot-650"], log, [slowdown] * 2,
                       radio_counted), log


def packs(wh):
    return [{"consumed_wh": w, "soc": 0.9, "voltage_v": 15.5} for w in wh]


def test_busy_is_cpu_time_on_the_runs_clock_and_air_time_is_bytes_at_the_phy_rate(tmp_path):
    """At 4x a host CPU second is 4 simulated seconds of the companion's; with a 6x device profile, 6."""
    m, log = meter(tmp_path)
    assert m.tick(10.0, packs([1.0, 1.0]), [5.0, 5.0], [(0, 0), (0, 0)], 4.0) == []
    rate = energy.RADIOS["wifi-router"].phy_rate_bps
    assert m.tick(12.0, packs([1.0 + 229.0 * 2 / 3600, 1.1]), [5.25, 5.1],
                  [(0, int(rate / 8)), (int(rate / 8 * 0.5), 0)], 4.0) == []
    log.close()
    m_rec, w_rec = read_jsonl(tmp_path / "energy.jsonl").of_kind("energy")
    assert m_rec["busy_share"] == pytest.approx(0.25 * 4 / 2) and w_rec["busy_share"] == pytest.approx(0.1 * 4 / 2)
    assert m_rec["tx_share"] == pytest.approx(0.5) and w_rec["rx_share"] == pytest.approx(0.25)
    assert m_rec["flight_w"] == pytest.approx(229.0, rel=1e-4) and w_rec["flight_w"] == pytest.approx(180.0)
    tx2 = energy.COMPANIONS["jetson-tx2"]
    assert w_rec["compute_w"] == pytest.approx(energy.companion_power_w(tx2, 0.2), abs=1e-3)
    assert m_rec["companion_w"] == pytest.approx((m_rec["compute_w"] + m_rec["radio_w"]) / 0.9, abs=1e-3)
    (tmp_path / "slow").mkdir()
    slow, log = meter(tmp_path / "slow", slowdown=6.0)
    slow.tick(0.0, packs([0, 0]), [0.0, 0.0], [None, None], 1.0)
    slow.tick(3.0, packs([0, 0]), [0.25, 1.0], [None, None], 1.0)
    log.close()
    shares = [r["busy_share"] for r in read_jsonl(tmp_path / "slow" / "energy.jsonl").of_kind("energy")]
    assert shares == [pytest.approx(0.5), 1.0], "6 x 0.25 s of 3 s; the rest capped at all of it"


def test_a_pack_that_empties_is_said_once_and_gives_nothing_after(tmp_path):
    m, log = meter(tmp_path, companion_mah=(1300.0, 0.01))
    m.tick(0.0, packs([0, 0]), [None, None], [None, None], 1.0)
    assert m.tick(5.0, packs([0, 0]), [None, None], [None, None], 1.0) == [1]
    assert m.tick(6.0, packs([0, 0]), [None, None], [None, None], 1.0) == []
    assert m.tick(6.5, packs([0, 0]), [None, None], [None, None], 1.0) == [], "not before a second has passed"
    log.close()
    w = [r for r in read_jsonl(tmp_path / "energy.jsonl").of_kind("energy") if r["vehicle"] == "w"]
    assert w[0]["companion_soc"] == 0.0 and w[1]["companion_w"] == 0.0 and w[1]["companion_v"] == 0.0


def test_proc_readers_measure_this_process_and_say_none_for_a_gone_one():
    cpu_s = process_cpu_s(os.getpid())
    assert cpu_s is not None and cpu_s > 0.0
    assert process_cpu_s(None) is None and process_cpu_s(2**22 + 12345) is None
    rx_tx = namespace_bytes(os.getpid())
    assert rx_tx is not None and all(v >= 0 for v in rx_tx)
    assert namespace_bytes(2**22 + 12345) is None


def test_a_slow_link_keeps_the_radio_on_longer_for_the_same_bytes(tmp_path):
    """1 Mbit sent in 2 s: at the radio's 65 Mbit/s PHY rate 0.8 % of the air, on a 5 Mbit/s link 10 %."""
    m, log = meter(tmp_path)
    m.tick(0.0, packs([0, 0]), [None, None], [(0, 0), (0, 0)], 1.0)
    m.tick(2.0, packs([0, 0]), [None, None], [(0, 125_000), (0, 125_000)], 1.0, [None, 5e6])
    log.close()
    fast, slow = read_jsonl(tmp_path / "energy.jsonl").of_kind("energy")
    assert fast["tx_share"] == pytest.approx(1e6 / 65e6 / 2, abs=1e-5) and fast["air_rate_bps"] == 65e6
    assert slow["tx_share"] == pytest.approx(0.1) and slow["air_rate_bps"] == 5e6
    assert slow["radio_w"] > fast["radio_w"]
