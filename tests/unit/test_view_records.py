"""The view's one reader, on files written as a live run writes them: whole lines only, damaged lines named,
kinds nobody wrote listed, positions in metres about the first one heard."""

import json

import pytest

from ground.view.records import RunFollower
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
    frames = frames[1:]
    assert frames[0]["e"] == pytest.approx(0.0, abs=0.01) and frames[0]["u"] == pytest.approx(10.0, abs=0.01)
    with agent.open("a") as f:  # the rest of that line, a damaged one, another position
        f.write(telemetry(3.0, 12.0, -5.0)[40:] + "{not json\n" + telemetry(4.0, 20.0, 30.0, mode="RTL"))
    frames = follower.poll()
    assert [(f["e"], f["n"], f["mode"]) for f in frames] == [(12.0, -5.0, "AUTO"), (20.0, 30.0, "RTL")]
    assert follower.problems == ["master/agent.jsonl:4: not a JSON record, skipped"]
    assert [f["s"] for f in follower.records] == [0, 1, 2, 3]
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
