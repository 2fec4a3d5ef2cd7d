"""Autopilot logs other tools wrote (../shared/data/realworld/tlog, bin, ulg; see its SOURCES.md): positions equal
the reference readers' (pymavlink, pyulog) row for row once samples without a fix are dropped, times on the base
each file allows (unix from GPS time, else seconds since boot, said), whatever the readers print goes into the
problems, and a run folder of such logs (uppercase extensions included) is analysed."""

import contextlib
import io
import math
import re
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ground.logs.analysis import analyze
from ground.logs.autopilot_logs import reader_for
from ground.logs.runlog import read_run
from nac_onboard.errors import BadInput
from tests.conftest import SHARED_DATA

REALWORLD = SHARED_DATA / "realworld"
# reading files, no clock: make test runs it beside the exclusive tests
pytestmark = [pytest.mark.skipif(not REALWORLD.is_dir(), reason=f"{REALWORLD} is absent (see the developers' guide)"),
              pytest.mark.niced]

#: file -> (positions, time base, words every listed problem must include, in order)
OUTCOMES = {
    "bin/joeydouglas__2014-10-18_21-12-23.bin": (104, "unix", []),  # 2014: GPS stamped with TimeMS, no TimeUS
    "bin/pymavlink__test.BIN": (23, "unix", []),
    "bin/rustdf__demo-flight.bin": (0, None, ["unpack requires a buffer", "bad header"]),
    "bin/yladzislay__dataflash-sample-2.bin": (520, "boot", ["cut short", "no GPS time in the log"]),
    "tlog/dronekitpy__flight.tlog": (2684, "unix", ["cut short", "149 of 2833 position samples taken without a 3D"]),
    "tlog/dronekitpy__test.tlog": (0, None, ["cut short", "11 of 11 position samples taken without a 3D fix"]),
    "tlog/mavlinklog__tlog_data_0.tlog": (0, None, ["36 of 36 position samples taken without a 3D fix"]),
    "tlog/uavlogviewer__vtol.tlog": (807, "unix", []),
    "ulg/px4ulogrs__6ba1abc7-b433-4029-b8f5-3b2bb12d3b6c.ulg": (129, "boot", ["no GPS UTC time"]),
    "ulg/px4ulogrs__corrupt_actuator_armed_wrong_size.ulg": (0, None, ["no GPS UTC time", "no positions"]),
    "ulg/pyulog__sample_appended_multiple.ulg": (0, None, ["no GPS UTC time", "no positions"]),
    "ulg/pyulog__sample_log_small.ulg": (32, "unix", ["no vehicle_global_position; positions are the GPS"]),
}


def test_every_log_in_the_folder_has_a_documented_outcome():
    found = sorted(str(p.relative_to(REALWORLD)) for kind in ("bin", "tlog", "ulg")
                   for p in (REALWORLD / kind).iterdir())
    assert found == sorted(OUTCOMES), "a new file in realworld/: give it its outcome here"


@pytest.mark.parametrize("name", sorted(OUTCOMES))
def test_a_real_log_reads_as_the_reference_reader_with_its_problems_said(name, capfd):
    path = REALWORLD / name
    rows, problems = reader_for(path)(path, "uav1")
    count, base, words = OUTCOMES[name]
    assert capfd.readouterr() == ("", ""), "nothing printed: the readers' complaints are problems of the file"
    assert len(rows) == count and {r["time_base"] for r in rows} <= {base}
    assert len(problems) >= len(words) and all(w in p for w, p in zip(words, problems, strict=False)), problems
    reference = [r[:3] for r in _reference(path) if not (r[1] == 0 and r[2] == 0) and r[3] is not False]
    assert len(reference) == len(rows)
    for row, (t_s, lat, lon) in zip(rows, reference, strict=True):
        assert (row["lat_deg"], row["lon_deg"]) == pytest.approx((lat, lon), abs=1e-9)
        if t_s is not None:
            assert row["t_s"] == pytest.approx(t_s, abs=1e-6)


def _reference(path: Path) -> list[tuple]:
    """(t_s or None, lat, lon, 3D fix or None where the sample does not say) of every position sample, as pymavlink
    or pyulog read the file: a tlog's GLOBAL_POSITION_INT has the fix of its vehicle's GPS_RAW_INT before it."""
    suffix = path.suffix.lower()
    if suffix == ".tlog":
        from pymavlink import mavutil

        conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
        out, fix = [], {}
        while (msg := conn.recv_match(type=["GLOBAL_POSITION_INT", "GPS_RAW_INT"])) is not None:
            if msg.get_type() == "GPS_RAW_INT":
                fix[msg.get_srcSystem()] = msg.fix_type >= 3
            else:
                out.append((msg._timestamp, msg.lat / 1e7, msg.lon / 1e7, fix.get(msg.get_srcSystem())))
        return out
    if suffix == ".bin":
        import contextlib
        import io

        from pymavlink import DFReader

        rows = {"POS": [], "GPS": []}
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            try:
                reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
                while (msg := reader.recv_match(type=["POS", "GPS"])) is not None:
                    rows[msg.get_type()].append((msg._timestamp, msg.Lat, msg.Lng,
                                                 msg.Status >= 3 if msg.get_type() == "GPS" else None))
            except Exception:  # the damaged file: what was read before
                pass
        return rows["POS"] or rows["GPS"]
    from pyulog import ULog

    ulog = ULog(str(path), message_name_filter_list=["vehicle_global_position", "vehicle_gps_position"])
    data = {d.name: d.data for d in ulog.data_list}
    if "vehicle_global_position" in data:
        d = data["vehicle_global_position"]
        return [(None, float(a), float(b), None) for a, b in zip(d["lat"], d["lon"], strict=True)]
    if "vehicle_gps_position" in data:
        d = data["vehicle_gps_position"]
        return [(None, a / 1e7, b / 1e7, f >= 3) for a, b, f in zip(d["lat"], d["lon"], d["fix_type"], strict=True)]
    return []


def test_a_folder_of_autopilot_logs_with_uppercase_names_is_analysed_and_clocks_are_explained(tmp_path):
    run = tmp_path / "run"
    for vehicle, name in (("copter", "bin/pymavlink__test.BIN"), ("old", "bin/yladzislay__dataflash-sample-2.bin")):
        (run / vehicle).mkdir(parents=True)
        shutil.copy(REALWORLD / name, run / vehicle / f"00000001{Path(name).suffix.upper()}")
    read = read_run(run)
    assert sorted(read.vehicles) == ["copter", "old"] and len(read.positions) == 23 + 520
    assert any("old: positions on seconds since boot" in p for p in read.problems), read.problems
    with pytest.raises(BadInput, match=r"--master nobody: no vehicle of that name in the run \(vehicles found: "
                                       r"copter, old\)"):
        analyze(read, master="nobody")
    tables = analyze(read, master="copter")
    assert tables.distances.empty and not math.isnan(tables.trajectories["lat_deg"].iloc[0])
    assert tables.trajectories["lat_deg"].abs().min() > 1.0, "no sample without a fix on the map"


def test_logs_analyze_takes_a_run_of_every_real_log_and_iperf3_file_with_no_traceback(tmp_path, capsys, caplog):
    """One vehicle folder per file, the iperf3 outputs on the master: exit 0, every file's problems named."""
    from ground import cli

    run = tmp_path / "run"
    for k, name in enumerate(sorted(OUTCOMES)):
        (run / f"v{k}").mkdir(parents=True)
        shutil.copy(REALWORLD / name, run / f"v{k}" / Path(name).name)
    for k, name in enumerate(sorted(IPERF3_OUTCOMES)):
        shutil.copy(REALWORLD / name, run / "v0" / f"iperf3-v{k + 1}.json")
    assert cli.main(["logs", "analyze", str(run), "--out", str(tmp_path / "report"), "--master", "v0"]) == 0
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err and "internal error" not in err
    said = caplog.text
    assert "rustdf__demo-flight.bin: unpack requires a buffer" in said and "iperf3-v2.json: iperf3 JSON" in said
    assert "v3, v8: positions on seconds since boot" in said
    assert (tmp_path / "report" / "report.md").is_file() and "report.md: 12 vehicles" in out, out


#: iperf3 --json output -> (received Mbit/s of the probe, or None where the file is skipped with this problem)
IPERF3_OUTCOMES = {
    "iperf3/cloudpilot-baseline__baseline_target_host_direct_10.res": (89.148, None),
    "iperf3/cloudpilot-failed__bw_host_proxy_proxy_0.res": (None, "never connected"),
    "iperf3/cloudpilot-omit3__bw_proxy_target_direct.res": (464.786, None),  # the 3 omitted seconds left out
}


def test_every_iperf3_file_in_the_folder_has_a_documented_outcome():
    assert sorted(f"iperf3/{p.name}" for p in (REALWORLD / "iperf3").iterdir()) == sorted(IPERF3_OUTCOMES)


@pytest.mark.parametrize("name", sorted(IPERF3_OUTCOMES))
def test_a_real_iperf3_file_is_a_probe_at_its_received_rate_or_skipped_with_the_reason(name, tmp_path):
    from ground.logs.runlog import iperf3_probes

    saved = tmp_path / "iperf3-w1.json"
    shutil.copy(REALWORLD / name, saved)
    probes, problems = iperf3_probes(saved, "master")
    rate_mbps, words = IPERF3_OUTCOMES[name]
    if rate_mbps is None:
        assert probes == [] and len(problems) == 1 and words in problems[0] and str(saved) in problems[0]
    else:
        [probe] = probes
        assert problems == [] and "error" not in probe and (probe["client"], probe["server"]) == ("master", "w1")
        assert probe["end"]["sum_received"]["bits_per_second"] / 1e6 == pytest.approx(rate_mbps, abs=1e-3)


def test_iperf3_results_appended_to_one_file_are_each_a_probe(tmp_path):
    """A flight script's `iperf3 --json >> file`: the three real results one after another, each read (the one
    that never connected skipped with its number); a damaged result is named by its number, those before it kept."""
    from ground.logs.runlog import iperf3_probes

    texts = [(REALWORLD / name).read_text() for name in sorted(IPERF3_OUTCOMES)]
    saved = tmp_path / "iperf3-w1.json"
    saved.write_text("".join(texts))
    probes, problems = iperf3_probes(saved, "master")
    assert [round(p["end"]["sum_received"]["bits_per_second"] / 1e6, 3) for p in probes] == [89.148, 464.786]
    assert len(problems) == 1 and "result 2:" in problems[0] and "never connected" in problems[0]
    saved.write_text(texts[0] + texts[2][:500])
    probes, problems = iperf3_probes(saved, "master")
    assert len(probes) == 1, "the result before the damage is kept"
    assert len(problems) == 1 and "not iperf3 JSON" in problems[0] and "result 2:" in problems[0]


MODERN_DATAFLASH = REALWORLD / "bin" / "yladzislay__dataflash-sample-2.bin"


def _both_readers(raw: bytes, tmp_path: Path) -> tuple[list | str, list | str]:
    """Rows (or the refusal) of the reader in use and of DFReader alone."""
    from ground.logs.autopilot_logs import FlightLogError, _dataflash_positions_dfreader, dataflash_positions

    path = tmp_path / "damaged.bin"
    path.write_bytes(raw)
    outcomes = []
    for read in (dataflash_positions, _dataflash_positions_dfreader):
        try:
            outcomes.append(read(path, "uav1")[0])
        except FlightLogError as err:
            outcomes.append(str(err))
    return outcomes[0], outcomes[1]


@pytest.mark.skipif(not MODERN_DATAFLASH.is_file(), reason=f"{MODERN_DATAFLASH} is absent")
def test_the_fast_dataflash_walk_ignores_header_bytes_inside_payloads_and_walks_over_damage(tmp_path):
    from ground.logs.dataflash import read_positions_fast

    raw = bytearray(MODERN_DATAFLASH.read_bytes())
    walked = read_positions_fast(bytes(raw))
    assert walked is not None and len(walked.columns["POS"]["TimeUS"]) == 520, "a modern log takes the fast path"
    # header bytes (and an FMT type) inside the last POS record's payload are not records
    payload_at = len(raw) // 2
    payload_at = raw.index(b"\xa3\x95", payload_at) + 3
    raw[payload_at + 1:payload_at + 4] = b"\xa3\x95\x80"
    fast, slow = _both_readers(bytes(raw), tmp_path)
    assert read_positions_fast(bytes(raw)) is not None and fast == slow and len(fast) == 520
    # bytes that are not a record in the middle: both readers go on at the next record, the fast walk says where
    raw[payload_at - 3:payload_at - 3] = bytes(range(256)) * 4
    walked = read_positions_fast(bytes(raw))
    assert walked is not None and walked.skipped == [(payload_at - 3, 1024)]
    fast, slow = _both_readers(bytes(raw), tmp_path)
    assert fast == slow and len(fast) == 520
    # an FMT that gives POS no longitude: no positions from POS, said, no crash
    columns_at = raw.index(b"TimeUS,Lat,Lng")
    raw[columns_at + 11:columns_at + 14] = b"Lxg"
    from ground.logs.autopilot_logs import dataflash_positions

    (tmp_path / "no-lng.bin").write_bytes(bytes(raw))
    rows, problems = dataflash_positions(tmp_path / "no-lng.bin", "uav1")
    assert rows == [] and any("POS records without the columns Alt, Lat, Lng" in p for p in problems), problems


@pytest.mark.skipif(not MODERN_DATAFLASH.is_file(), reason=f"{MODERN_DATAFLASH} is absent")
def test_a_header_of_no_known_type_mid_log_is_skipped_and_every_position_after_it_read(tmp_path):
    """The damaged ArduCopter log of issue 31: a header whose type no FMT defines, then garbage. DFReader's index
    stops there, so a read by type (ours once, the fast walk's and the fallback's) lost every position after it,
    where DFReader's record-by-record read finds them all."""
    from pymavlink import DFReader

    from ground.logs.autopilot_logs import dataflash_positions

    raw = bytearray(MODERN_DATAFLASH.read_bytes())
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        reader = DFReader.DFReader_binary(str(MODERN_DATAFLASH), zero_time_base=False)
    pos_type = reader.name_to_id["POS"]
    at = next(o for o in reader.offsets[pos_type] if o > len(raw) // 3)  # a POS record's start
    unknown = max(set(range(256)) - set(reader.formats))
    raw[at:at] = bytes([0xA3, 0x95, unknown]) + bytes(range(40, 80))
    path = tmp_path / "damaged.bin"
    path.write_bytes(bytes(raw))
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        reader, every = DFReader.DFReader_binary(str(path), zero_time_base=False), 0
        while (msg := reader.recv_msg()) is not None:
            every += msg.get_type() == "POS"
    rows, problems = dataflash_positions(path, "uav1")
    assert len(rows) == every == 520
    skips = [re.fullmatch(rf"{re.escape(str(path))}: (\d+) bytes at offset (\d+) are not records \(damage\); "
                          r"skipped to the next record", p) for p in problems]
    (skip_bytes, offset), = [(int(m[1]), int(m[2])) for m in skips if m]
    assert (offset, skip_bytes) == (at, 43), "the skip names the inserted bytes and their place"
    fast, slow = _both_readers(bytes(raw), tmp_path)
    assert fast == slow == rows


@pytest.mark.skipif(not MODERN_DATAFLASH.is_file(), reason=f"{MODERN_DATAFLASH} is absent")
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 749_567), st.integers(0, 255)), min_size=1, max_size=8))
def test_a_damaged_dataflash_log_gives_the_rows_dfreader_gives(flips, tmp_path):
    """Where DFReader itself fails on the damage (one byte of an FMT record: "object of type 'NoneType' has no
    len()"), there is nothing to compare with: ours may read on past it, and a flipped byte can make at most one
    record out of nothing."""
    raw = bytearray(MODERN_DATAFLASH.read_bytes())
    for at, value in flips:
        raw[at % len(raw)] = value
    fast, slow = _both_readers(bytes(raw), tmp_path)
    if isinstance(slow, str) and "not a DataFlash log (" in slow and not isinstance(fast, str):
        assert len(fast) <= 520 + len(flips)
    else:
        assert fast == slow


def test_a_file_that_is_not_a_dataflash_log_is_said_in_one_sentence(tmp_path):
    """An SITL eeprom image named like a log: one sentence, not DFReader's thousands of "bad header" lines."""
    from ground.logs.autopilot_logs import FlightLogError, dataflash_positions

    path = tmp_path / "eeprom.bin"
    path.write_bytes(bytes(range(256)) * 256)
    with pytest.raises(FlightLogError) as refused:
        dataflash_positions(path, "uav1")
    assert str(refused.value) == (f"{path}: not a DataFlash log: no FMT record in its first 4096 bytes (an "
                                  f"ArduPilot .bin log starts with one: bytes A3 95 80)")
