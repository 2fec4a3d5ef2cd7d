"""The view's one reader, on files written as a live run writes them: whole lines only, damaged lines named,
kinds nobody wrote listed, positions in metres about the first one heard."""

import json

import pytest

from ground.view.records import RunFollower, positions
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
    assert frames["it"] == {"k": "it", "t": 2.5, "i": 0, "dur": 0.4, "cost": 3.5, "n": 1, "of": 2,
                            "s": frames["it"]["s"]}
    assert frames["ev"]["text"] == "fault: link_down on for w1" and frames["ev"]["fault"]
    assert follower.vehicles["w1"] == {"role": "worker"}
    assert follower.missions_m()["master"][0] == pytest.approx([0.0, 50.0], abs=0.05)
    assert follower.problems == ["experiment.json:3: not a JSON record, skipped"], "NaN is not JSON"
    follower.finish()


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
