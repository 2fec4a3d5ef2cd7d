"""The radio model against hand-computed values and textbook statistics (issue 15, acceptance 1 and 2)."""

from __future__ import annotations

import cmath
import dataclasses
import math

import numpy as np
import pytest

from nac_onboard.link.emulation import SleepEmulation
from nac_onboard.radio import air_link
from nac_onboard.radio.channel import PRESETS, ChannelModel
from sitl.telemetry_radio import TELEMETRY_RADIOS

# computation only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced


def model(**fields) -> ChannelModel:
    base = dict(name="t", path_loss="log-distance", freq_mhz=2437.0, bandwidth_hz=20e6, tx_power_dbm=15.0,
                noise_w=1e-13, exponent=3.0, ref_loss_db=50.0)
    return ChannelModel(**{**base, **fields})


def test_two_ray_matches_the_phasor_sum_and_its_far_field_asymptote():
    # d 20 m between antennas at 3 m and 3 m, 2437 MHz, vertical polarization over ground of permittivity 15
    lam = 299_792_458.0 / 2437e6
    d_ref = math.hypot(20.0, 6.0)
    sin_psi, eps = 6.0 / d_ref, 15.0
    root = math.sqrt(eps - (1 - sin_psi ** 2))
    gamma = (eps * sin_psi - root) / (eps * sin_psi + root)
    field = cmath.exp(-2j * math.pi * 20.0 / lam) / 20.0 + gamma * cmath.exp(-2j * math.pi * d_ref / lam) / d_ref
    by_hand = -20 * math.log10(lam / (4 * math.pi) * abs(field))
    assert gamma == pytest.approx(0.06915, abs=1e-4), "just past the Brewster angle: a weak reflection"
    assert air_link.two_ray_db(20.0, 3.0, 3.0, 2437.0) == pytest.approx(by_hand, abs=1e-9)
    # far beyond the breakpoint 4 h_a h_b / lambda (~300 m), horizontal polarization: 40 log d - 20 log(h_a h_b)
    assert air_link.two_ray_db(20_000.0, 3.0, 3.0, 2437.0, polarization="horizontal") == pytest.approx(
        40 * math.log10(20_000.0) - 20 * math.log10(9.0), abs=0.3)
    # heights are live: a vehicle on the ground (0.1 m) hears its peer worse than one hovering at 3 m, far away
    assert air_link.two_ray_db(500.0, 0.1, 3.0, 2437.0) > air_link.two_ray_db(500.0, 3.0, 3.0, 2437.0) + 20


def test_dual_slope_bends_at_its_breakpoint():
    assert air_link.dual_slope_db(5.0, 40.0, 2.0, 10.0, 4.0) == pytest.approx(40 + 20 * math.log10(5))
    assert air_link.dual_slope_db(10.0, 40.0, 2.0, 10.0, 4.0) == pytest.approx(60.0)
    assert air_link.dual_slope_db(100.0, 40.0, 2.0, 10.0, 4.0) == pytest.approx(100.0)
    assert model(path_loss="dual-slope", ref_loss_db=40.0, exponent=2.0, breakpoint_m=10.0,
                 exponent_far=4.0).path_loss_db(100.0) == pytest.approx(100.0)


def test_mcs_selection_at_the_thresholds():
    m = model(rate_model="802.11n", min_rate_bps=1e5)
    thresholds = air_link.HT_SNR_THRESHOLDS_DB
    assert air_link.frame_error_rate(thresholds, thresholds, 1.0) == pytest.approx(np.full(8, 0.1))
    for k in (0, 2, 3, 4):  # the next threshold 3 dB or more away: just above one, that MCS; 3 dB below, lower
        assert air_link.link_rates(m, thresholds[k] + 0.5).mcs[0] == k
    for k in range(1, 8):
        assert air_link.link_rates(m, thresholds[k] - 3.0).mcs[0] < k
    top = air_link.link_rates(m, 40.0)
    assert top.mcs[0] == 7 and top.phy_bps[0] == 65e6 and top.loss[0] < 1e-12
    wide = air_link.link_rates(dataclasses.replace(m, channel_width_mhz=40, short_guard_interval=True), 40.0)
    assert wide.phy_bps[0] == 150e6
    assert not air_link.link_rates(m, 0.0).in_range[0], "below MCS 0 nothing gets through"
    edge = air_link.link_rates(m, thresholds[0] - 2.0)
    assert 0 < edge.loss[0] < 1 and edge.per[0] > 0.3, "near MCS 0's threshold frames fail and some packets are lost"


def test_median_throughput_against_distance_steps_through_the_mcs_table():
    wifi = PRESETS["wifi-flight"]
    distances = np.linspace(1.0, 24.0, 200)
    mcs = air_link.link_rates(wifi, wifi.median_snr_db(distances)).mcs
    assert set(mcs.tolist()) == set(range(8)) and np.all(np.diff(mcs) <= 0)
    band = air_link.rate_band(wifi, [10.0, 20.0], draws=4000)
    assert np.all(band["low_bps"] < band["median_bps"]) and np.all(band["median_bps"] < band["high_bps"])


def test_gudmundson_shadowing_decorrelates_with_the_distance_moved():
    sigma, d_corr, step_m = 4.0, 10.0, 2.0
    r = air_link.Radio(model(shadowing_sigma_db=sigma, shadowing_decorrelation_m=d_corr), 1, seed=3)
    values = []
    for _ in range(8_000):
        r.step(0.1, [10.0], moved_m=[step_m])
        values.append(r.shadow_db[0])
    s = np.array(values)
    assert np.corrcoef(s[:-1], s[1:])[0, 1] == pytest.approx(math.exp(-step_m / d_corr), abs=0.02)
    assert np.corrcoef(s[:-5], s[5:])[0, 1] == pytest.approx(math.exp(-5 * step_m / d_corr), abs=0.03)
    assert s.std() == pytest.approx(sigma, rel=0.05)
    before = r.shadow_db.copy()
    r.step(0.1, [10.0], moved_m=[0.0])
    assert r.shadow_db == pytest.approx(before), "a static pair keeps its offset"


def test_rician_power_has_the_textbook_mean_and_variance():
    k_db = 6.0
    r = air_link.Radio(model(rician_k_db=k_db), 10_000, seed=5)
    sample = r.step(0.0, np.full(10_000, 10.0))
    power = 10 ** ((sample.snr_db - model().median_snr_db(10.0)) / 10)
    mean, variance = air_link.rician_power_moments(10 ** (k_db / 10))
    assert power.mean() == pytest.approx(mean, rel=0.03)
    assert power.var() == pytest.approx(variance, rel=0.03)


def test_fading_decorrelates_faster_when_the_pair_moves():
    def lag_one(speed_mps: float) -> float:
        r = air_link.Radio(model(rician_k_db=3.0, hover_speed_mps=0.2), 1, seed=11)
        snr = [r.step(0.1, [10.0], speed_mps=[speed_mps]).snr_db[0] for _ in range(5000)]
        return float(np.corrcoef(snr[:-1], snr[1:])[0, 1])

    assert lag_one(0.0) > 0.6 > 0.3 > lag_one(1.34)
    assert air_link.bessel_j0(np.array([0.0, 2.404825557695773, 5.0])) == pytest.approx([1.0, 0.0, -0.1775968],
                                                                                        abs=1e-6)


def _probe_std_mbps(moving: bool, seconds: int = 400, seed: int = 2) -> tuple[float, float]:
    """1-second probes of a pair 12 m apart: one vehicle still, the other hovering or circling it at 0.67 m/s."""
    air = air_link.AirRadio(PRESETS["wifi-flight"], 2, seed=seed)
    rates, distances = [], []
    for step in range(seconds * 10):
        t = step / 10
        angle = 0.67 * t / 12.0 if moving else 0.0
        positions = np.array([[0.0, 0.0, 3.0], [12.0 * math.cos(angle), 12.0 * math.sin(angle), 3.0]])
        d, sample = air.step(t, positions)
        rates.append(sample.goodput_bps[0])
        distances.append(d[0])
    probes = np.array(rates).reshape(seconds, 10).mean(axis=1) / 1e6
    return float(probes.std()), float(np.mean(distances))


def test_a_static_link_varies_a_little_and_a_moving_one_more():
    """Pooled over four seeded pairs: how much one static link's probes vary depends on where its one shadowing
    draw puts its SNR against the MCS thresholds (2.0-5.5 Mbit/s over these seeds), while the circling one
    crosses some 27 decorrelation lengths in its 200 s. Seeded: the same figures on every host."""
    static, moving = [], []
    for seed in range(4):
        static_std, static_d = _probe_std_mbps(moving=False, seconds=200, seed=seed)
        moving_std, moving_d = _probe_std_mbps(moving=True, seconds=200, seed=seed)
        assert static_d == pytest.approx(moving_d)
        static.append(static_std)
        moving.append(moving_std)
    assert min(static) > 0 and np.mean(moving) > 1.25 * np.mean(static), (static, moving)


def test_sleep_emulation_steps_each_pair_and_charges_a_timeout_for_a_lost_packet():
    emulation = SleepEmulation(PRESETS["wifi-flight"])
    near = [emulation.link(10.0, "w1").capacity_bps for _ in range(3)]
    assert len(emulation.pairs) == 1 and all(r > 0 for r in near)
    emulation.link(10.0, "w2")
    assert len(emulation.pairs) == 2
    assert emulation.transfer_s(8_000, 8e6) == pytest.approx(1e-3)
    assert emulation.transfer_s(8_000, 8e6, loss=1.0) == pytest.approx(1e-3 + 0.2)
    assert not emulation.link(60.0, "w1").in_range


def test_nac_sitl_radio_prints_the_curve_with_its_band_and_steps(capsys):
    import io

    from sitl import cli

    text = io.StringIO()
    cli.radio_table("wifi-flight", "2,10,20,30", 500, text)
    out = text.getvalue()
    rows = [line.split() for line in out.splitlines() if line.strip() and line.split()[0] in ("2", "10", "20", "30")]
    assert [int(r[1]) for r in rows[:3]] == sorted((int(r[1]) for r in rows[:3]), reverse=True), "MCS steps down"
    assert all(float(r[3]) <= float(r[2]) <= float(r[4]) for r in rows), "median inside its 95 % band"
    assert len(rows) == 4 and "sources:" in out and "p97.5_mbps" in out
    assert cli.main(["radio", "wifi-flight", "--distances-m", "ten"]) == 2
    assert "--distances-m" in capsys.readouterr().err


def test_a_replay_table_round_trips_interpolates_and_names_a_bad_file(tmp_path):
    from nac_onboard.radio.files import load_replay, save_replay
    from nac_onboard.radio.replay import ReplayError, ReplayLinks

    table = ReplayLinks("run-x", {("master", "w1"): (np.array([0.0, 10.0]), np.array([20e6, 10e6]))})
    save_replay(table, tmp_path / "replay.json")
    back = load_replay(tmp_path / "replay.json")
    assert back.rate_bps("w1", "master", 5.0) == pytest.approx(15e6) and back.rate_bps("w1", "w2", 5.0) is None
    assert back.rate_bps("master", "w1", -3.0) == 20e6 and back.rate_bps("master", "w1", 99.0) == 10e6
    (tmp_path / "bad.json").write_text('{"pairs": [{"a": "m", "b": "w", "t_s": [2, 1], "rate_bps": [1, 2]}]}')
    with pytest.raises(ReplayError, match="bad.json: not a replay table .*pair 1: .*times rising"):
        load_replay(tmp_path / "bad.json")
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ReplayError, match="list.json: not a replay table"):
        load_replay(tmp_path / "list.json")


def test_the_telemetry_radio_loses_more_frames_further_out_and_lower_down():
    sik = TELEMETRY_RADIOS["sik-915"]
    loss = sik.frame_loss(np.array([100.0, 1000.0, 3000.0, 10_000.0]), 30.0)
    assert loss[0] < 1e-6 and np.all(np.diff(loss) > 0) and loss[-1] > 0.99
    assert 1000 < sik.range_m(30.0) < 5000, "stock SiK radios reach a few kilometres"
    assert sik.range_m(3.0) < sik.range_m(30.0), "two-ray: a low antenna hears less far"
    assert sik.received_dbm(500.0, 30.0) == pytest.approx(
        20.0 + 4.0 - 25.0 - air_link.two_ray_db(500.0, 1.5, 30.0, 915.0))


def test_two_workers_talk_through_the_access_point_not_over_their_own_distance():
    """Infrastructure mode: a worker pair is shaped as its two hops through the master (the access point). Two
    workers 30 m apart on either side of the master (past wifi-flight's range directly, 15 m from the master each)
    still reach each other, at the two hops' rate in series and either hop's loss, on either air; one out of the
    master's range reaches nobody. (The MPI job's start-up needs every pair: an ad hoc pair out of range hung it.)"""
    from sitl.network.shaping import air_state, through_the_ap

    rate = np.array([[0.0, 30e6, 10e6], [30e6, 0.0, 0.0], [10e6, 0.0, 0.0]])
    loss = np.array([[0.0, 0.1, 0.2], [0.1, 0.0, 1.0], [0.2, 1.0, 0.0]])
    relayed, relayed_loss = through_the_ap(rate, loss, ap=0)
    assert relayed[1, 2] == relayed[2, 1] == pytest.approx(7.5e6) and relayed_loss[1, 2] == pytest.approx(0.28)
    assert (relayed[0] == rate[0]).all() and (relayed_loss[:, 0] == loss[:, 0]).all(), "the AP's own pairs stay"
    rate[0, 2] = rate[2, 0] = 0.0
    relayed, relayed_loss = through_the_ap(rate, loss, ap=0)
    assert relayed[1, 2] == 0.0 and relayed_loss[1, 2] == 1.0, "out of the AP's range: out of everyone's"

    positions = np.array([[0.0, 0.0, 0.0], [-15.0, 0.0, 0.0], [15.0, 0.0, 0.0]])
    direct = air_link.AirRadio(PRESETS["wifi-flight"], 3, seed=1)
    _, sample = direct.step(0.0, positions)
    assert not direct.matrix(sample.in_range)[1, 2], "30 m: out of range on their own"
    state = air_state(air_link.AirRadio(PRESETS["wifi-flight"], 3, seed=1), 0.0, positions, ap=0, sharing=True)
    assert state.rate_bps[1, 2] > 0 and state.loss[1, 2] < 1.0
    up, down = state.frames["phy_bps"][1, 0], state.frames["phy_bps"][0, 2]
    assert state.frames["phy_bps"][1, 2] == pytest.approx(1 / (1 / up + 1 / down)), "the frame-level air's too"
    ad_hoc = air_state(air_link.AirRadio(PRESETS["wifi-flight"], 3, seed=1), 0.0, positions, ap=None, sharing=False)
    assert ad_hoc.rate_bps[1, 2] == 0.0


def test_shadowing_after_a_path_does_not_depend_on_how_often_it_was_stepped():
    """The same 6 m climb stepped 60 times or 7 times, unevenly, ends at the same offset (it used to be whatever
    the steps had drawn), and a pair that did not move keeps its first one."""
    wifi = model(shadowing_sigma_db=4.0, shadowing_decorrelation_m=5.0)
    fine, coarse = air_link.Radio(wifi, 2, seed=9), air_link.Radio(wifi, 2, seed=9)
    for _ in range(60):
        fine.step(0.05, [10.0, 10.0], moved_m=[0.1, 0.0])
    for step_m in (0.3, 1.7, 0.05, 2.0, 0.95, 0.5, 0.5):
        coarse.step(0.4, [10.0, 10.0], moved_m=[step_m, 0.0])
    assert fine.shadow_db == pytest.approx(coarse.shadow_db, abs=1e-9)
    assert fine.shadow_db[1] == air_link.Radio(wifi, 2, seed=9).shadow_db[1]
    assert abs(fine.shadow_db[0] - fine.shadow_db[1]) > 1e-3, "the climbing pair's offset moved"


def test_the_radios_line_names_the_mac_it_charges():
    """A report's radio line says what a frame costs: the preset's MAC efficiency on the htb air and the sleep network,
    the 802.11 medium's own costs (and its retry limit) on the frame-level air, where the efficiency is not used."""
    wifi = PRESETS["wifi-flight"]
    assert wifi.describe().endswith(f"MAC efficiency {wifi.mac_efficiency:g}")
    frame_level = dataclasses.replace(wifi, mac="802.11", retry_limit=4).describe()
    assert "MAC efficiency" not in frame_level and frame_level.endswith(
        "the 802.11 MAC frame by frame (channel access, preamble and block ack per aggregate, retry limit 4)")
