"""The view's one reader, on files written as a live run writes them: whole lines only, damaged lines named,
kinds nobody wrote listed, positions in metres about the first one heard."""

import json

import pytest

from ground.view.records import (
    MAX_FRAME_POSITIONS,
    MAX_GAP_S,
    MAX_ID_CHARS,
    MAX_LINE_BYTES,
    MAX_TEXT_CHARS,
    RunFollower,
    positions,
)
from missions.geo import Home, enu_to_lla

ORIGIN = Home(47.397742, 8.545594, 488.0)


def telemetry(t_s, east, north, up=10.0, **extra):
    lat, lon, alt = enu_to_lla([east, north, up], ORIGIN)
    return json.dumps({"t_s": t_s, "kind": "telemetry", "lat_deg": float(lat), "lon_deg": float(lon),
                       "alt_m": float(alt), "rel_alt_m": up, "yaw_deg": 90.0, "mode": "AUTO", "armed": True,
                       "time_boot_ms": int(t_s * 1000), **extra}) + "\n"


def test_a_live_run_is_read_as_it_is_written_and_damage_is_named(tmp_path):
    (tmp_path / "master").mkdir()
    agent = tmp_path / "master" / "agent.jsonl"
    follower = RunFollower(tmp_path)
    assert follower.poll() == [], "nothing yet: no error"
    agent.write_text(json.dumps({"t_s": 1.0, "kind": "agent_started", "role": "master"}) + "\n"
                     + telemetry(2.0, 0.0, 0.0) + telemetry(3.0, 12.0, -5.0)[:40])  # the last line half written
    frames = follower.poll()
    assert [f["k"] for f in frames] == ["ev", "pos"] and follower.vehicles == {"master": {"role": "master"}}
    assert frames[0]["text"] == "master: agent started"
    first = positions(frames)
    assert len(first) == 1 and first[0]["v"] == "master" and first[0]["t"] == 2.0
    assert first[0]["e"] == pytest.approx(0.0, abs=0.01) and first[0]["u"] == pytest.approx(10.0, abs=0.01)
    with agent.open("a") as f:  # the rest of that line, a damaged one, another position
        f.write(telemetry(3.0, 12.0, -5.0)[40:] + "{not json\n" + telemetry(4.0, 20.0, 30.0, mode="RTL"))
    frames = follower.poll()
    assert len(frames) == 1, "one read of a vehicle's file: one batch of positions"
    assert [(p["e"], p["n"], p["mode"], p["hdg"], p["armed"]) for p in positions(frames)] == \
        [(12.0, -5.0, "AUTO", 90.0, True), (20.0, 30.0, "RTL", 90.0, True)]
    assert follower.problems == ["master/agent.jsonl:4: not a JSON record, skipped"]
    assert [f["s"] for f in follower.records] == [0, 1, 2] and follower.record_count == 4
    assert follower.missing() == ["throughput probes (throughput.jsonl)", "compute iterations (compute.jsonl)",
                                  "link model capacities (network.jsonl, SITL)"]


def test_a_sped_up_runs_rates_and_durations_are_per_simulated_second_as_in_the_report(tmp_path):
    """At 5x a probe's iperf3 figures count wall seconds: the page shows them per simulated second, as the
    report, the progress line and the records' own `speedup` say (issue 33: labels 5x the report's)."""
    (tmp_path / "master").mkdir()
    (tmp_path / "compute").mkdir()
    (tmp_path / "master" / "throughput.jsonl").write_text(json.dumps(
        {"t_s": 2.0, "kind": "throughput", "client": "master", "server": "w1", "speedup": 5.0,
         "end": {"sum_received": {"bits_per_second": 1.5e8}}}) + "\n")
    (tmp_path / "compute" / "compute.jsonl").write_text(json.dumps(
        {"t_s": 2.5, "kind": "iteration", "iteration": 0, "duration_s": 0.06, "start_sim_s": 40.0,
         "duration_sim_s": 0.3, "workers": {"present": [True]}}) + "\n")
    frames = {f["k"]: f for f in RunFollower(tmp_path).poll()}
    assert frames["probe"]["bps"] == pytest.approx(3e7) and frames["probe"]["ok"]
    assert frames["it"]["dur"] == 0.3 and frames["it"]["ts"] == 40.0


def test_probes_iterations_faults_and_missions_become_frames(tmp_path):
    (tmp_path / "master").mkdir()
    (tmp_path / "compute").mkdir()
    (tmp_path / "master" / "agent.jsonl").write_text(telemetry(1.0, 0.0, 0.0))
    (tmp_path / "master" / "throughput.jsonl").write_text(
        json.dumps({"t_s": 2.0, "kind": "throughput", "client": "master", "server": "w1", "distance_m": 9.0,
                    "end": {"sum_received": {"bits_per_second": 2.5e7}}}) + "\n"
        + json.dumps({"t_s": 3.0, "kind": "throughput", "client": "master", "server": "w1", "error": "timeout"})
        + "\n")
    (tmp_path / "compute" / "compute.jsonl").write_text(json.dumps(
        {"t_s": 2.5, "kind": "iteration", "iteration": 0, "duration_s": 0.4, "cost": 3.5,
         "workers": {"present": [True, False]}}) + "\n")
    north = enu_to_lla([0.0, 50.0, 0.0], ORIGIN)
    (tmp_path / "experiment.json").write_text(
        json.dumps({"t_s": 0.5, "kind": "experiment", "vehicles": [{"id": "w1", "role": "worker"}],
                    "missions": {"master": [[float(north[0]), float(north[1])]]}}) + "\n"
        + json.dumps({"t_s": 2.7, "kind": "fault", "vehicle": "w1", "fault": "link_down", "state": "on"}) + "\n"
        + '{"t_s": NaN, "kind": "fault"}\n')
    follower = RunFollower(tmp_path)
    frames = {f["k"]: f for f in follower.poll()}
    assert frames["probe"]["bps"] == 0.0 and not frames["probe"]["ok"], "the failed probe is the last"
    assert frames["it"] == {"k": "it", "t": 2.5, "i": 0, "dur": 0.4, "ts": None, "cost": 3.5, "n": 1, "of": 2,
                            "s": frames["it"]["s"]}
    assert frames["ev"]["text"] == "fault: link_down on for w1" and frames["ev"]["fault"]
    assert follower.vehicles["w1"] == {"role": "worker"}
    assert follower.missions_m()["master"][0] == pytest.approx([0.0, 50.0], abs=0.05)
    assert follower.problems == ["experiment.json:3: not a JSON record, skipped"], "NaN is not JSON"
    follower.finish()


def test_each_vehicles_two_packs_become_frames_in_percent_and_nonsense_is_not_a_number(tmp_path):
    (tmp_path / "master").mkdir()
    (tmp_path / "master" / "agent.jsonl").write_text(telemetry(1.0, 0.0, 0.0))
    (tmp_path / "energy.jsonl").write_text("".join(json.dumps(
        {"t_s": 2.0 + k, "kind": "energy", "vehicle": vehicle, "flight_soc": flight, "companion_soc": companion})
        + "\n" for k, (vehicle, flight, companion) in enumerate(
            (("master", 0.974, 0.5), ("w1", 1.7, -3.0), ("w1", "full", None)))))
    frames = [f for f in RunFollower(tmp_path).poll() if f["k"] == "pw"]
    assert [(f["v"], f["fs"], f["cs"]) for f in frames] == [("master", 97, 50), ("w1", 100, 0), ("w1", None, None)]


def test_positions_that_are_not_finite_numbers_on_the_globe_are_not_drawn_and_values_are_typed(tmp_path):
    """Hostile or damaged fields: a position needs finite numbers (not strings, bools, null) within the globe;
    the rest of a record is passed on only as the type the page expects."""
    (tmp_path / "w1").mkdir()
    good = json.loads(telemetry(1.0, 5.0, 5.0))
    bad_values = [{"lat_deg": "47.4"}, {"lon_deg": True}, {"alt_m": None}, {"lat_deg": 91.0}, {"lon_deg": -181.0}]
    lines = [json.dumps({**good, "t_s": 2.0 + k, **bad}) for k, bad in enumerate(bad_values)]
    lines.append(json.dumps({**good, "t_s": 9.0, "mode": "<b>x</b>" * 20, "armed": "yes", "battery_pct": "full",
                             "mission_seq": 3, "yaw_deg": "east", "time_boot_ms": None}))
    (tmp_path / "w1" / "agent.jsonl").write_text(telemetry(1.0, 5.0, 5.0) + "\n".join(lines) + "\n")
    drawn = positions(RunFollower(tmp_path).poll())
    assert [p["t"] for p in drawn] == [1.0, 9.0]
    last = drawn[-1]
    assert (last["mode"], last["armed"], last["batt"], last["seq"], last["hdg"], last["tb"]) == \
        (("<b>x</b>" * 5), None, None, 3, None, None)


@pytest.mark.parametrize("size", [MAX_LINE_BYTES - 100, MAX_LINE_BYTES + 1, 3 * MAX_LINE_BYTES + 17])
def test_a_record_over_the_line_limit_is_skipped_and_named_without_being_held(tmp_path, size):
    """A valid record longer than MAX_LINE_BYTES (a statustext padded to `size` bytes), written live in pieces
    around other records: skipped and named with its line and size, never held whole, the records after it
    read; one just under the limit is read."""
    (tmp_path / "w1").mkdir()
    agent = tmp_path / "w1" / "agent.jsonl"
    head = '{"t_s": 2.0, "kind": "statustext", "severity": 6, "text": "'
    big = head + "x" * (size - len(head) - 3) + '"}\n'
    assert len(big) == size
    follower = RunFollower(tmp_path)
    agent.write_text(telemetry(1.0, 0.0, 0.0))
    follower.poll()
    for k in range(0, len(big), 700_000):  # the line arrives as a writer's buffers would
        with agent.open("a") as f:
            f.write(big[k:k + 700_000])
        follower.poll()
        assert all(len(tail.partial) <= MAX_LINE_BYTES for tail in follower._tails.values())
    with agent.open("a") as f:
        f.write(telemetry(3.0, 5.0, 0.0))
    follower.poll()
    follower.finish()
    assert [p["t"] for p in positions(follower.records)] == [1.0, 3.0], "the records around it are read"
    if size - 1 > MAX_LINE_BYTES:  # the newline is not the record's
        assert follower.problems == [f"w1/agent.jsonl:2: a record of {size - 1:,} bytes, over the "
                                     f"{MAX_LINE_BYTES:,}-byte limit, skipped"]
        assert not any(f["k"] == "ev" for f in follower.records)
    else:
        assert follower.problems == [] and [f["text"][:20] for f in follower.records if f["k"] == "ev"] == \
            ["w1: says " + "x" * 11], "read, and its text cut short for the page"
        assert max(len(f["text"]) for f in follower.records if f["k"] == "ev") <= MAX_TEXT_CHARS + 20


def test_an_oversized_last_line_of_a_finished_run_is_named(tmp_path):
    (tmp_path / "w1").mkdir()
    (tmp_path / "w1" / "agent.jsonl").write_text(telemetry(1.0, 0.0, 0.0) + "y" * (MAX_LINE_BYTES + 5))
    follower = RunFollower(tmp_path)
    follower.finish()
    assert follower.problems == [f"w1/agent.jsonl:2: a record of {MAX_LINE_BYTES + 5:,} bytes, over the "
                                 f"{MAX_LINE_BYTES:,}-byte limit, skipped"]


WILD_T_S = [1e15, -1e15, 1e300, 5e9, 1020.0 + MAX_GAP_S, 1000.0 - MAX_GAP_S - 60.0, 2e9 + 3 * MAX_GAP_S]


@pytest.mark.parametrize("first_is_wild", [False, True])
def test_records_far_outside_the_runs_time_are_skipped_and_named(tmp_path, first_is_wild):
    """The run's time is where most of its first records are (a wild first line does not decide it); a record
    more than a day from the records kept, or a day ahead of the clock, is skipped and named, in any file."""
    for vid in ("master", "w1"):
        (tmp_path / vid).mkdir()
    lines = [telemetry(1000.0 + k, float(k), 0.0) for k in range(20)]
    wild = [telemetry(t, 50.0, 0.0) for t in WILD_T_S]
    master = (wild[:1] + lines + wild[1:]) if first_is_wild else (lines[:10] + wild + lines[10:])
    (tmp_path / "master" / "agent.jsonl").write_text("".join(master))
    (tmp_path / "w1" / "agent.jsonl").write_text(
        "".join(json.dumps({"t_s": t, "kind": "mode", "value": "AUTO"}) + "\n" for t in (1005.0, 1e15)))
    (tmp_path / "master" / "throughput.jsonl").write_text(json.dumps(
        {"t_s": -1e300, "kind": "throughput", "client": "master", "server": "w1"}) + "\n")
    follower = RunFollower(tmp_path)
    follower.finish()
    kept = [p["t"] for p in positions(follower.records)]
    assert kept == [1000.0 + k for k in range(20)]
    assert follower.span == (1000.0, 1019.0)
    assert [f["t"] for f in follower.records if f["k"] == "ev"] == [1005.0]
    assert len(follower.problems) == len(WILD_T_S) + 2
    assert all("t_s" in p and ("more than a day" in p) and p.endswith("skipped") for p in follower.problems)
    assert any(p.startswith("w1/agent.jsonl:2: t_s 1000000000000000.0 ") for p in follower.problems)
    assert any(p.startswith("master/throughput.jsonl:1: t_s -1e+300") for p in follower.problems)


def test_a_long_live_run_moves_its_span_with_its_records(tmp_path):
    """The span grows with each record kept: records a few hours apart over several days are all kept; a jump of
    more than a day is not."""
    (tmp_path / "w1").mkdir()
    follower = RunFollower(tmp_path)
    times = [1e6 + k * 6 * 3600.0 for k in range(12)]  # three days, a record every six hours
    with (tmp_path / "w1" / "agent.jsonl").open("a") as f:
        for t in times:
            f.write(telemetry(t, 0.0, 0.0))
            f.flush()
            follower.poll()
        f.write(telemetry(times[-1] + MAX_GAP_S + 1.0, 0.0, 0.0))
    follower.poll()
    assert [p["t"] for p in positions(follower.records)] == times and len(follower.problems) == 1


def test_names_and_texts_from_records_reach_the_page_short_and_as_strings(tmp_path):
    (tmp_path / "master").mkdir()
    (tmp_path / "master" / "throughput.jsonl").write_text(json.dumps(
        {"t_s": 1.0, "kind": "throughput", "client": "m" * 5000, "server": {"x": [1] * 1000}}) + "\n")
    (tmp_path / "network.jsonl").write_text(
        json.dumps({"t_s": 1.0, "kind": "link_rates", "a": ["master", {"x": 1}], "b": ["w1", "w" * 900],
                    "rate_bps": [1e6, "fast"], "distance_m": [3.0, None]}) + "\n"
        + json.dumps({"t_s": 1.5, "kind": "link_rates", "a": ["master"], "b": [], "rate_bps": 5,
                      "distance_m": []}) + "\n")
    frames = RunFollower(tmp_path).poll()
    probe = next(f for f in frames if f["k"] == "probe")
    assert len(probe["a"]) == MAX_ID_CHARS and len(probe["b"]) == MAX_ID_CHARS
    caps = [f for f in frames if f["k"] == "cap"]
    assert len(caps) == 1, "columns that are not lists of one length draw nothing"
    assert caps[0]["a"] == ["master", "{'x': 1}"] and caps[0]["b"] == ["w1", "w" * MAX_ID_CHARS]
    assert caps[0]["bps"] == [1e6, None] and caps[0]["d"] == [3.0, None]


def test_a_frame_holds_a_bounded_number_of_positions(tmp_path):
    (tmp_path / "w1").mkdir()
    count = MAX_FRAME_POSITIONS * 2 + 5
    line = json.loads(telemetry(1000.0, 0.0, 0.0))
    (tmp_path / "w1" / "agent.jsonl").write_text(
        "".join(json.dumps({**line, "t_s": 1000.0 + k * 0.01}) + "\n" for k in range(count)))
    frames = RunFollower(tmp_path).poll()
    assert [len(f["t"]) for f in frames] == [MAX_FRAME_POSITIONS, MAX_FRAME_POSITIONS, 5]
    assert len(positions(frames)) == count
