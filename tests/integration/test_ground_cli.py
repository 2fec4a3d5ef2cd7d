"""`nac-ground` against the SITL over real UDP, run as the operator runs it: one process per command."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from missions import load_mission
from missions.geo import Home, enu_to_lla
from nac_onboard.mavlink.signing import load_signing_key

EXAMPLES = Path(__file__).resolve().parents[2] / "missions" / "examples"
SCENARIOS = {  # vehicle index -> example file, as missions/examples/README.md assigns them
    "paper-sim": ["paper-sim-master.plan", "paper-sim-worker1.plan", "paper-sim-worker2.plan",
                  "paper-sim-worker3.plan"],
    "flight-test": ["flight-test-master.plan", "flight-test-worker1.plan", "flight-test-worker2.plan"],
}


def ground(*args, timeout_s: float = 120.0):
    return subprocess.run([sys.executable, "-m", "ground.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s)


def link(sim, vehicle: int) -> str:
    return f"udpin:127.0.0.1:{sim.config.gcs_base_port + sim.config.port_step * vehicle}"


def ok(result):
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr}"
    return result


def test_every_example_file_is_covered():
    assert sorted(p.name for p in EXAMPLES.glob("*.plan")) == sorted(sum(SCENARIOS.values(), []))


@pytest.mark.parametrize("scenario", sorted(SCENARIOS))
def test_examples_upload_download_equal_and_fly_to_completion(scenario, start_sitl, tmp_path):
    files = SCENARIOS[scenario]
    # Each command is a process of its own: at 25x, ArduCopter's 10 s DISARM_DELAY is 0.4 s of wall time between
    # `arm` and `mission start`, less than a loaded machine takes to start the next one. 0 turns it off.
    sim = start_sitl(vehicles=len(files), speedup=25.0, spacing_m=5.0, params={"DISARM_DELAY": 0})
    for i, name in enumerate(files):
        path = EXAMPLES / name
        ok(ground("--connect", link(sim, i), "mission", "upload", str(path)))
        back = tmp_path / f"back-{i}.plan"
        ok(ground("--connect", link(sim, i), "mission", "download", str(back)))
        assert load_mission(back).same_items_as(load_mission(path)), f"{name} did not read back item for item"
        ok(ground("--connect", link(sim, i), "arm"))
        ok(ground("--connect", link(sim, i), "mission", "start"))
    for i, name in enumerate(files):
        done = ok(ground("--connect", link(sim, i), "wait", "mission-complete", "--timeout-s", "60"))
        assert "mission complete" in done.stdout
        ok(ground("--connect", link(sim, i), "wait", "landed", "--timeout-s", "30"))
        assert sim.truth(i)["on_ground"], name


def test_commands_report_refusals_with_exit_1(start_sitl):
    sim = start_sitl(speedup=10.0, params={"DISARM_DELAY": 0})  # one process per command: see the test above
    refused = ground("--connect", link(sim, 0), "mission", "start")
    assert refused.returncode == 1 and "MAV_RESULT_FAILED" in refused.stderr
    ok(ground("--connect", link(sim, 0), "arm"))
    ok(ground("--connect", link(sim, 0), "takeoff", "5"))
    ok(ground("--connect", link(sim, 0), "mode", "loiter"))
    ok(ground("--connect", link(sim, 0), "rtl"))
    ok(ground("--connect", link(sim, 0), "wait", "landed", "--timeout-s", "60"))
    assert sim.truth(0)["mode"] == "RTL" and sim.truth(0)["on_ground"]
    in_rtl = ground("--connect", link(sim, 0), "arm")  # the vehicle's reason travels with its refusal
    assert in_rtl.returncode == 1 and "MAV_RESULT_FAILED" in in_rtl.stderr, in_rtl.stderr
    assert 'it said: "Arm: mode RTL does not allow arming"' in in_rtl.stderr and not sim.truth(0)["armed"]
    ok(ground("--connect", link(sim, 0), "mode", "loiter"))
    unarmed = ground("--connect", link(sim, 0), "takeoff", "5")
    assert unarmed.returncode == 1 and '"Takeoff refused: arm first"' in unarmed.stderr, unarmed.stderr
    assert "back in LOITER" in unarmed.stdout and sim.truth(0)["mode"] == "LOITER", "a refusal changes nothing"
    alone = ground("--connect", link(sim, 0), "--sysid", "7", "status", "--listen-s", "1")
    assert alone.returncode == 1 and "vehicle 7 not heard" in alone.stderr and "(heard: 1)" in alone.stderr
    nobody = ground("--connect", "udpin:127.0.0.1:9", "status", "--listen-s", "0.5")
    assert nobody.returncode == 1 and "no vehicle heard on udpin:127.0.0.1:9" in nobody.stderr
    bad_mode = ground("--connect", link(sim, 0), "mode", "WARP")
    assert bad_mode.returncode == 2 and "unknown mode 'WARP'" in bad_mode.stderr
    silent = ground("--connect", "udpin:127.0.0.1:9", "--wait-s", "0.5", "arm")
    assert silent.returncode == 1 and "no heartbeat" in silent.stderr


def test_signing_same_key_works_missing_or_wrong_key_is_refused_and_explained(start_sitl, tmp_path):
    key_file = tmp_path / "fleet.key"
    key_file.write_text("nac test fleet key\n")
    sim = start_sitl(speedup=5.0, signing_key=load_signing_key(key_file), params={"DISARM_DELAY": 0})
    wrong_file = tmp_path / "wrong.key"
    wrong_file.write_text("another key\n")

    unsigned = ground("--connect", link(sim, 0), "arm")
    assert unsigned.returncode == 1 and "signing" in unsigned.stderr
    wrong = ground("--connect", link(sim, 0), "--signing-key-file", str(wrong_file), "--wait-s", "2", "arm")
    assert wrong.returncode == 1 and "signing key differs" in wrong.stderr
    assert not sim.truth(0)["armed"]
    ok(ground("--connect", link(sim, 0), "--signing-key-file", str(key_file), "arm"))
    assert sim.truth(0)["armed"]


def test_status_and_monitor_show_all_four_vehicles(start_sitl):
    sim = start_sitl(vehicles=4, speedup=5.0)
    connects = sum((["--connect", link(sim, i)] for i in range(4)), [])
    table = ok(ground(*connects, "status")).stdout.splitlines()
    assert table[0].split()[:3] == ["SYSID", "MODE", "ARMED"]
    rows = [line.split() for line in table[1:]]
    assert [row[0] for row in rows] == ["1", "2", "3", "4"]
    for i, row in enumerate(rows):
        assert row[1] == "STABILIZE" and row[2] == "no"
        assert abs(float(row[3]) - sim.homes[i].lat_deg) < 1e-6 and abs(float(row[4]) - sim.homes[i].lon_deg) < 1e-6
    live = ok(ground(*connects, "monitor", "--duration-s", "2.5", "--refresh-s", "1")).stdout
    frames = [block for block in live.split("\n\n") if block.strip()]
    assert len(frames) >= 2
    assert [line.split()[0] for line in frames[-1].splitlines()[2:]] == ["1", "2", "3", "4"]


def test_validate_and_convert_work_offline(tmp_path):
    source = EXAMPLES / "flight-test-master.plan"
    checked = ok(ground("mission", "validate", str(source)))
    assert "valid" in checked.stdout
    wpl = tmp_path / "master.waypoints"
    ok(ground("mission", "convert", str(source), str(wpl)))
    assert wpl.read_text().startswith("QGC WPL 110\n")
    back = tmp_path / "master.plan"
    ok(ground("mission", "convert", str(wpl), str(back)))
    assert load_mission(back).same_items_as(load_mission(source))
    missing = ground("mission", "validate", str(tmp_path / "nope.plan"))
    assert missing.returncode == 2 and "nope.plan" in missing.stderr


def test_several_vehicles_through_one_link(start_sitl):
    """All vehicles sending to one port (port step 0), as through one telemetry radio: told apart by sysid."""
    sim = start_sitl(vehicles=3, speedup=5.0, port_step=0, params={"DISARM_DELAY": 0})
    rows = ok(ground("--connect", link(sim, 0), "status")).stdout.splitlines()[1:]
    assert [row.split()[0] for row in rows] == ["1", "2", "3"]
    ok(ground("--connect", link(sim, 0), "--sysid", "2", "arm"))
    assert [sim.truth(i)["armed"] for i in range(3)] == [False, True, False]


def test_client_sets_the_current_item_and_reads_telemetry_state(start_sitl):
    from nac_onboard.mavlink.client import CommandError, MavlinkClient

    sim = start_sitl(speedup=5.0)
    with MavlinkClient(link(sim, 0)) as client:
        client.wait_heartbeat()
        ok(ground("--connect", link(sim, 0), "mission", "upload", str(EXAMPLES / "paper-sim-master.plan")))
        client.set_current(2)
        assert client.recv("MISSION_CURRENT", 3.0, lambda m: m.seq == 2) is not None
        with pytest.raises(CommandError, match="MAV_RESULT_DENIED"):
            client.set_current(99)
        client.poll(1.5)
        state = client.vehicles[1]
        assert state.mode == "STABILIZE" and not state.armed and state.landed == "on ground"
        assert abs(state.lat_deg - sim.homes[0].lat_deg) < 1e-6 and state.battery_pct == 100
        assert state.mission_seq == 2 and state.mission_total == len(load_mission(
            EXAMPLES / "paper-sim-master.plan").items)
        assert state.link_age_s() < 1.5


def test_the_telemetry_radio_loses_frames_with_distance_to_the_ground_station(start_sitl):
    """A SiK-class radio on the ground link, the ground station 270 m from a landed vehicle (antenna 0.1 m up):
    about a third of the frames are lost, the upload still lands item for item on the vehicle (retries); 3 km
    away nothing gets through and the upload fails in its time with a sentence, not a hang."""
    home = Home(47.397742, 8.545594, 488.0)
    near = Home(*enu_to_lla(np.array([0.0, 270.0, 0.0]), home))
    sim = start_sitl(speedup=5.0, home=home, telemetry_radio="sik-915", ground_station=near)
    sim.step_once()
    assert 0.15 < sim.ground_loss[0] < 0.7
    path = EXAMPLES / "flight-test-master.plan"
    ok(ground("--connect", link(sim, 0), "mission", "upload", str(path)))
    on_vehicle, sent = sim.world.autopilots.mission(0), load_mission(path).items
    assert len(on_vehicle) == len(sent) + 1 and all(a.same_as(b) for a, b in zip(on_vehicle[1:], sent, strict=True))
    assert sim.stats["radio_lost"] > 10, "frames were lost on the way"
    far = start_sitl(speedup=5.0, home=home, telemetry_radio="sik-915",
                     ground_station=Home(*enu_to_lla(np.array([0.0, 3000.0, 0.0]), home)))
    far.step_once()
    assert far.ground_loss[0] > 0.999
    refused = ground("--connect", link(far, 0), "mission", "upload", str(path), timeout_s=60.0)
    assert refused.returncode == 1 and "Traceback" not in refused.stderr, refused.stderr
    assert len(far.world.autopilots.mission(0)) <= 1, "nothing was installed"
