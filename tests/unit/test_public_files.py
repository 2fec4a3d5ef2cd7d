"""Public files of the kinds issue 31 found NAC misreading (tests/data/public, each with its source in SOURCES.md),
each checked against what the reference tool makes of it: MAVSDK's importer (its own tests' verdicts on its own
plans), MAVProxy's loaders (pymavlink's mavwp), pyulog, pymavlink's DFReader and mavutil, and real iperf3."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import DFReader, mavutil, mavwp

from ground.logs.autopilot_logs import MIN_FIX_TYPE, dataflash_positions, tlog_positions, ulog_positions
from ground.logs.runlog import iperf3_probes
from missions import MissionFileError, load_mission
from missions.model import MavCmd
from nac_onboard.mavlink.dialect import mission_catalogue
from sitl.launcher import free_port
from tests.conftest import SHARED_DATA

PUBLIC = Path(__file__).resolve().parents[1] / "data" / "public"


@pytest.mark.parametrize("name, complex_item", [
    ("survey/qgroundcontrol_sample_with_survey_missing_items.plan", 'ComplexItem "survey"'),
    ("structure_scan/qgroundcontrol_sample_with_structured_scan.plan", 'ComplexItem "StructureScan"')])
def test_a_complex_item_that_stores_no_items_is_refused_by_name_as_mavsdk_refuses_it(name, complex_item):
    """MAVSDK's mission_import_test expects FailedToParseQgcPlan for both files (no stored items to upload)."""
    with pytest.raises(MissionFileError) as refused:
        load_mission(PUBLIC / name, flight=False, catalogue=mission_catalogue())
    assert f"item 2 ({complex_item}): stores no mission items" in str(refused.value)


def test_a_plan_without_a_mission_section_is_refused_as_mavsdk_refuses_it():
    with pytest.raises(MissionFileError) as refused:
        load_mission(PUBLIC / "fence_rally_only_plan" / "qgroundcontrol_sample_without_mission.plan", flight=False)
    assert 'missing field "mission"' in str(refused.value)


@pytest.mark.parametrize("name", ["ce_geofence_home_base.plan", "ce_geofence_rd_2.plan"])
def test_a_fence_only_plan_gives_its_polygons_vertex_by_vertex_as_qgc_uploads_them(name):
    """QGC's geofence upload: each polygon's vertices in order, as NAV_FENCE_POLYGON_VERTEX_INCLUSION (5001) or
    EXCLUSION (5002) with param1 the polygon's vertex count; the empty mission is no reason to refuse the file."""
    path = PUBLIC / "fence_rally_only_plan" / name
    plan = json.loads(path.read_text())
    expected = [(MavCmd.NAV_FENCE_POLYGON_VERTEX_INCLUSION if polygon["inclusion"] else
                 MavCmd.NAV_FENCE_POLYGON_VERTEX_EXCLUSION, len(polygon["polygon"]), lat, lon)
                for polygon in plan["geoFence"]["polygons"] for lat, lon in polygon["polygon"]]
    mission = load_mission(path)
    assert not mission.items and len(expected) == 8
    assert [(it.command, it.p1, it.lat_deg, it.lon_deg) for it in mission.fence] == expected


def _mavwp(protocol, path: Path) -> list:
    loader = protocol(target_system=1, target_component=1)
    loader.load(str(path))
    return [loader.item(k) for k in range(loader.count())]


@pytest.mark.parametrize("name", sorted(p.name for p in (PUBLIC / "mavproxy_rally_old").iterdir()))
def test_mavproxys_old_rally_files_give_the_points_mavproxy_loads(name):
    """pymavlink's loader writes z as the file's altitude times 1,000, where MISSION_ITEM_INT's z for a rally point
    is metres (MAVLink's common.xml; QGC and ArduPilot read it so): NAC keeps the file's metres."""
    path = PUBLIC / "mavproxy_rally_old" / name
    theirs = _mavwp(mavwp.MissionItemProtocol_Rally, path)
    ours = load_mission(path).rally
    assert theirs and [(it.command, it.frame, it.alt_m) for it in ours] == \
        [(w.command, w.frame, w.z / 1e3) for w in theirs]
    for it, w in zip(ours, theirs, strict=True):  # mavwp truncates to 1e-7 degrees, NAC rounds
        assert abs(it.lat_deg * 1e7 - w.x) <= 1 and abs(it.lon_deg * 1e7 - w.y) <= 1


@pytest.mark.parametrize("name", sorted(p.name for p in (PUBLIC / "mavproxy_fence_old").iterdir()))
def test_mavproxys_old_fence_files_give_the_fence_mavproxy_loads(name):
    path = PUBLIC / "mavproxy_fence_old" / name
    theirs = _mavwp(mavwp.MissionItemProtocol_Fence, path)
    ours = load_mission(path).fence
    assert [(it.command, it.frame, it.p1) for it in ours] == [(w.command, w.frame, w.param1) for w in theirs]
    for it, w in zip(ours, theirs, strict=True):  # mavwp truncates to 1e-7 degrees, NAC rounds
        assert abs(it.lat_deg * 1e7 - w.x) <= 1 and abs(it.lon_deg * 1e7 - w.y) <= 1


def test_a_ulog_whose_gps_had_no_fix_gives_the_fixed_samples_pyulog_reads():
    """The issue's file: no vehicle_global_position, and 160 of vehicle_gps_position's 190 samples without a 3D
    fix (146 with none, 14 with 2D)."""
    from pyulog import ULog

    path = PUBLIC / "log_without_fix" / "sample_logging_tagged_and_default_params.ulg"
    gps = next(d.data for d in ULog(str(path), ["vehicle_gps_position"]).data_list)
    fixed = gps["fix_type"] >= MIN_FIX_TYPE
    rows, problems = ulog_positions(path, "uav1")
    assert (len(gps["fix_type"]), int(fixed.sum())) == (190, 30)
    expected = zip((gps["lat"][fixed] / 1e7).tolist(), (gps["lon"][fixed] / 1e7).tolist(), strict=True)
    assert [(r["lat_deg"], r["lon_deg"]) for r in rows] == list(expected)
    assert any("160 of 190 position samples taken without a 3D fix" in p for p in problems), problems


def test_a_tlog_whose_gps_lost_its_fix_gives_the_positions_pymavlink_reads_with_one():
    """dronekit-python's flight.tlog (realworld/tlog): GPS_RAW_INT says fix type 1 for part of the flight."""
    path = SHARED_DATA / "realworld" / "tlog" / "dronekitpy__flight.tlog"
    if not path.exists():
        pytest.skip(f"{path} is absent (see the developers' guide)")
    log, fix, expected = mavutil.mavlink_connection(str(path)), None, []
    while (msg := log.recv_match(type=["GPS_RAW_INT", "GLOBAL_POSITION_INT"])) is not None:
        if msg.get_type() == "GPS_RAW_INT":
            fix = msg.fix_type
        elif fix is not None and fix >= MIN_FIX_TYPE:
            expected.append((msg.lat / 1e7, msg.lon / 1e7))
    rows, problems = tlog_positions(path)
    assert [(r["lat_deg"], r["lon_deg"]) for r in rows] == expected
    assert any("without a 3D fix" in p for p in problems), problems


def test_a_cut_arducopter_4_6_log_gives_the_positions_dfreader_reads_record_by_record():
    """ArduCopter V4.6.2 on a Pixhawk 4, cut at 80 KiB mid-record (MethodicConfigurator's fixture)."""
    path = PUBLIC / "dataflash_damaged" / "backend_log_80k.bin"
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        reader, expected = DFReader.DFReader_binary(str(path), zero_time_base=False), []
        while (msg := reader.recv_msg()) is not None:
            if msg.get_type() == "POS":
                expected.append((msg.Lat, msg.Lng, msg.Alt))
    rows, problems = dataflash_positions(path, "uav1")
    assert expected and [(r["lat_deg"], r["lon_deg"], r["alt_m"]) for r in rows] == expected
    assert problems == [f"{path}: 2 bytes after the last record are not a record; skipped"]


def _listening(port: int) -> bool:
    """Whether a TCP socket listens on the port (the kernel's table: connecting would count as an iperf3 test)."""
    rows = Path("/proc/net/tcp").read_text().splitlines()[1:]
    return any(int(row.split()[1].split(":")[1], 16) == port and row.split()[3] == "0A" for row in rows)


@pytest.mark.skipif(shutil.which("iperf3") is None, reason="iperf3 is not installed (.ci/run installs it)")
def test_iperf3_results_appended_by_a_flight_script_are_each_read(tmp_path):
    """Real iperf3 output, as `iperf3 -c PEER --json >> iperf3-PEER.json` leaves it after two tests."""
    port = free_port()
    server = subprocess.Popen(["iperf3", "--server", "--bind", "127.0.0.1", "--port", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out = tmp_path / "iperf3-w1.json"
    try:
        deadline = time.monotonic() + 10.0
        while not _listening(port):  # the server binds in its own time
            assert server.poll() is None and time.monotonic() < deadline, "iperf3 --server did not listen"
            time.sleep(0.02)
        for _ in range(2):
            done = subprocess.run(["iperf3", "--client", "127.0.0.1", "--port", str(port), "--bytes", "4M",
                                   "--json"], capture_output=True, text=True, timeout=20)
            with out.open("a") as appended:
                appended.write(done.stdout)
    finally:
        server.terminate()
        server.wait(timeout=10)
    probes, problems = iperf3_probes(out, "master")
    sent = [json.loads(part) for part in out.read_text().replace("}\n{", "}\n\x00{").split("\x00")]
    assert problems == [] and len(probes) == 2
    assert [p["end"]["sum_received"]["bits_per_second"] for p in probes] == \
        [s["end"]["sum_received"]["bits_per_second"] for s in sent]
    assert np.all(np.diff([p["t_s"] for p in probes]) >= 0)
