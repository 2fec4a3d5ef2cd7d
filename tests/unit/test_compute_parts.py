"""The computing model's pure parts: channel models against hand-computed values, kernels, the data set."""

import hashlib
import io
import math
import os
import zipfile

import numpy as np
import pytest

from nac_onboard.compute import forestfires, kernels
from nac_onboard.compute.launch import core_binding, cpu_per_host, mpiexec_command
from nac_onboard.compute.positions import ScriptedDistances
from nac_onboard.errors import BadInput
from nac_onboard.radio.channel import PRESETS, ChannelError, ChannelModel
from nac_onboard.radio.files import load_channel, save_channel
from tests.conftest import SHARED_DATA

CSV = SHARED_DATA / "forestfires.csv"


def hata(env: str) -> ChannelModel:
    return ChannelModel(name="t", path_loss=f"hata-{env}", freq_mhz=1200.0, bandwidth_hz=1e6, tx_power_dbm=20.0,
                        noise_w=1e-12, base_height_m=30.0, mobile_height_m=1.5)


@pytest.mark.parametrize("env, at_1km_db, at_10m_db", [
    # By hand: D = 69.55 + 26.16 lg1200 - 13.82 lg30 - a(1.5) = 129.660, E = 44.9 - 6.55 lg30 = 35.225.
    ("urban", 129.660, 59.211),
    ("large-city", 129.688, 59.239),  # a(h_m) = 3.2 (lg 17.625)^2 - 4.97 = -0.0008
    ("suburban", 118.933, 48.484),  # - 2 (lg(1200/28))^2 - 5.4 = -10.727
    ("rural", 99.841, 29.391),  # - 4.78 (lg1200)^2 + 18.33 lg1200 - 40.94 = -29.820
])
def test_hata_okumura_matches_hand_computed_losses(env, at_1km_db, at_10m_db):
    model = hata(env)
    assert model.path_loss_db(1000.0) == pytest.approx(at_1km_db, abs=0.005)
    assert model.path_loss_db(10.0) == pytest.approx(at_10m_db, abs=0.005)
    assert "extrapolation" in model.validity()


def test_free_space_log_distance_and_shannon_by_hand():
    fs = ChannelModel("fs", "free-space", 2437.0, 20e6, 0.0, 1e-12)
    assert fs.path_loss_db(10.0) == pytest.approx(60.187, abs=0.001)  # 20 + 187.737 - 147.55
    ld = ChannelModel("ld", "log-distance", 2437.0, 20e6, 10.0, 1e-12, exponent=3.0, ref_loss_db=40.0)
    assert ld.path_loss_db(10.0) == pytest.approx(70.0)
    assert ld.received_dbm(10.0) == pytest.approx(-60.0)
    # -60 dBm = 1e-9 W over 1e-12 W of noise: SNR 1000, C = 20 MHz * log2(1001) = 199.34 Mbit/s.
    assert ld.capacity_bps(10.0) == pytest.approx(199.3445e6, rel=1e-5)
    default_ref = ChannelModel("ld2", "log-distance", 2437.0, 20e6, 0.0, 1e-12, exponent=2.0)
    assert default_ref.path_loss_db(10.0) == pytest.approx(fs.path_loss_db(10.0)), "n = 2 from free space at 1 m"


def test_presets_behave_as_documented():
    wifi = PRESETS["wifi-flight"]
    assert 20.0 <= wifi.range_m() <= 25.0, "throughput falls to ~0 near 20-25 m, as in the flight tests"
    assert wifi.capacity_bps(9.8) > wifi.capacity_bps(12.8) > wifi.capacity_bps(17.0) > 0
    assert not wifi.in_range(30.0)
    paper = PRESETS["paper-sim"]
    assert (paper.freq_mhz, paper.bandwidth_hz, paper.noise_w) == (1200.0, 1200e6, 1.1e-35)
    assert paper.capacity_bps(9.43) > paper.capacity_bps(12.8) > paper.capacity_bps(17.0)


def test_channel_files_round_trip_and_errors_name_the_file(tmp_path):
    path = tmp_path / "calibrated.toml"
    save_channel(PRESETS["wifi-flight"], path)
    assert load_channel(str(path)) == PRESETS["wifi-flight"]
    (tmp_path / "bad.toml").write_text('path_loss = "log-distance"\nfreq_mhz = 2437\nbandwidth_hz = 2e7\n'
                                       'tx_power_dbm = 15\nnoise_w = 1e-12\ncolour = "red"\n')
    with pytest.raises(ChannelError, match="bad.toml: unknown key colour"):
        load_channel(str(tmp_path / "bad.toml"))
    with pytest.raises(ChannelError, match="not a preset"):
        load_channel("moon-link")
    with pytest.raises(ChannelError, match="path_loss must be one of"):
        ChannelModel("x", "three-ray", 2437.0, 20e6, 0.0, 1e-12)


def test_split_rows_equal_and_proportional():
    assert kernels.split_rows(100, [1, 1, 1]) == [(0, 33), (33, 67), (67, 100)]
    assert kernels.split_rows(517, [1, 1]) == [(0, 258), (258, 517)]
    assert kernels.split_rows(100, [3, 1]) == [(0, 75), (75, 100)]
    with pytest.raises(ValueError):
        kernels.split_rows(10, [0, 0])


def test_shard_gradients_combine_into_the_full_gradient():
    rng = np.random.default_rng(1)
    x, y, w = rng.standard_normal((50, 4)), rng.standard_normal(50), rng.standard_normal(4)
    full, full_cost, _ = kernels.combine_gradients([kernels.local_gradient(x, y, w)])
    parts = [kernels.local_gradient(x[a:b], y[a:b], w) for a, b in kernels.split_rows(50, [1, 2, 3])]
    gradient, cost, rows = kernels.combine_gradients(parts)
    assert rows == 50 and np.allclose(gradient, full, atol=1e-12) and cost == pytest.approx(full_cost)
    assert np.allclose(full, x.T @ (x @ w - y) / 50)
    partial, _, rows = kernels.combine_gradients(parts[:1])
    assert rows == len(parts[0][0]) * 0 + parts[0][2], "a missing shard: the others, weighted by their size"
    assert np.allclose(partial, parts[0][0] / parts[0][2])


def test_forest_fires_features_and_gradient_descent():
    x, y = forestfires.load(CSV)
    assert x.shape == (517, len(forestfires.FEATURES)) == (517, 30)
    assert np.allclose(x[:, 0], 1.0) and np.allclose(x[:, 1:11].mean(axis=0), 0, atol=1e-12)
    assert np.allclose(x[:, 1:11].std(axis=0), 1.0)
    assert np.all(x[:, 11:23].sum(axis=1) == 1) and np.all(x[:, 23:].sum(axis=1) == 1)
    assert y.min() == 0.0 and y.max() == pytest.approx(math.log1p(1090.84))
    _, costs = kernels.gradient_descent(x, y, np.zeros(30), 0.05, 200)
    assert all(b < a for a, b in zip(costs, costs[1:], strict=False))


def test_data_is_found_in_order_and_missing_data_is_explained(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.setenv("NAC_DATA_DIR", str(SHARED_DATA))
    assert forestfires.find_csv() == CSV
    assert forestfires.find_csv(str(CSV)) == CSV
    monkeypatch.setenv("NAC_DATA_DIR", str(tmp_path / "nowhere"))
    with pytest.raises(forestfires.DataError, match="nac-onboard data fetch"):
        forestfires.find_csv()
    with pytest.raises(forestfires.DataError, match="missing.csv"):
        forestfires.find_csv(str(tmp_path / "missing.csv"))


def test_malformed_csv_names_the_line(tmp_path):
    lines = CSV.read_text().splitlines()
    bad = tmp_path / "bad.csv"
    fields = lines[2].split(",")
    fields[2] = "smarch"
    bad.write_text("\n".join([lines[0], lines[1], ",".join(fields)]))
    with pytest.raises(forestfires.DataError, match=r"bad.csv: line 3: unknown month"):
        forestfires.load(bad)
    bad.write_text("\n".join([lines[0], lines[1] + ",7"]))
    with pytest.raises(forestfires.DataError, match="line 2: expected 13 fields, got 14"):
        forestfires.load(bad)


def test_fetch_takes_the_csv_out_of_the_archive_and_checks_its_hash(tmp_path):
    data = CSV.read_bytes()
    assert hashlib.sha256(data).hexdigest() == forestfires.CSV_SHA256
    for name, content in (("good.zip", data), ("tampered.zip", data.replace(b"mar", b"apr", 1))):
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as z:
            z.writestr("forestfires.names", "about")
            z.writestr("forestfires.csv", content)
        (tmp_path / name).write_bytes(buf.getvalue())
    stored = forestfires.fetch((tmp_path / "good.zip").as_uri(), dest_dir=tmp_path / "cache")
    assert stored.read_bytes() == data
    with pytest.raises(forestfires.DataError, match="expected 0d6586a1"):
        forestfires.fetch((tmp_path / "tampered.zip").as_uri(), dest_dir=tmp_path / "other")
    assert not (tmp_path / "other" / "forestfires.csv").exists()


def test_scripted_distances_are_piecewise_constant():
    script = ScriptedDistances("iteration", {1: [(0, 10.0)], 2: [(0, 10.0), (50, 40.0), (80, 10.0)]})
    assert script.distances_m(49, 0.0) == {1: 10.0, 2: 10.0}
    assert script.distances_m(50, 0.0)[2] == 40.0 and script.distances_m(79, 0.0)[2] == 40.0
    assert script.distances_m(80, 0.0)[2] == 10.0


def test_core_binding_gives_the_master_its_own_core_when_ranks_share_cores():
    assert core_binding(2, cores=2) == "core" and core_binding(3, cores=4) == "core"
    assert core_binding(3, cores=2) == "user:0,1,1"
    assert core_binding(5, cores=3) == "user:0,1,2,1,2"
    assert core_binding(4, cores=1) == "core"


def test_each_host_gets_the_core_its_rank_would_be_bound_to():
    assert cpu_per_host(["m", "w1", "w2"], cores=2) == {"m": 0, "w1": 1, "w2": 1}
    assert cpu_per_host(["m", "w1"], cores=4) == {"m": 0, "w1": 1}
    assert cpu_per_host(["m", "w1"], cores=1) == {}


def test_the_job_gets_a_proxy_per_host_and_no_clean_up_that_kills_the_survivors(tmp_path):
    command = mpiexec_command(["m", "w1", "w2"], tmp_path, env={"A": "1"})
    assert "-disable-auto-cleanup" in command and command[command.index("-ppn") + 1] == "1"
    assert command[command.index("-n") + 1] == "3" and command[-3:] == ["-genv", "A", "1"]
    assert (tmp_path / "hostfile").read_text() == "m:1\nw1:1\nw2:1\n"
    launcher = (tmp_path / "launcher").read_text()
    assert "ip netns" not in launcher and os.access(tmp_path / "launcher", os.X_OK)
    mpiexec_command(["a", "b"], tmp_path, netns=True)
    assert "ip netns exec" in (tmp_path / "netns-launcher").read_text()


@pytest.mark.parametrize("hosts", [["m", "m"], ["m", "w 1"], ["m", "w1;reboot"], ["-x", "w1"]])
def test_host_names_that_would_break_the_launcher_are_refused(tmp_path, hosts):
    with pytest.raises(BadInput, match="MPI host"):
        mpiexec_command(hosts, tmp_path)

