"""Scenario files: the shipped ones load and agree with their missions; bad ones are refused by name and key."""

import json
import os
import re
import types

import pytest

from missions.geo import distance_m
from nac_onboard.radio.channel import PRESETS
from sitl import cli
from sitl.experiment.commands import Ports, compute_args, kernel_mpi_command
from sitl.experiment.scenario import SCENARIO_DIR, ScenarioError, load_scenario

SHIPPED = sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))
TWO = ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
       "role = 'worker'\nhome = [47, 8, 500]\n")  # the smallest valid scenario: a master and a worker, no missions


def test_the_shipped_scenarios_load_with_the_research_geometry():
    assert SHIPPED == ["coded-edge", "energy-aware", "energy-equal", "paper-flight-moving", "paper-flight-static",
                       "paper-sim-moving", "paper-sim-static", "range-sweep", "uncoded-edge"]
    scenarios = {name: load_scenario(name) for name in SHIPPED}
    for s in scenarios.values():
        assert s.master.role == "master" and s.workers
        for v in s.vehicles:
            first = v.mission.items[0]
            assert first.command == 22, f"{s.name}/{v.id}: takes off where it stands"
    def spacing(name):
        s = scenarios[name]
        home = s.master.home
        return [round(distance_m(vars(home), vars(w.home)), 2) for w in s.workers]
    assert spacing("paper-sim-static") == [9.43, 12.8, 17.0]
    assert spacing("paper-flight-static") == [9.8, 8.9]
    assert scenarios["paper-sim-moving"].compute.iterations == 40 and scenarios["paper-sim-moving"].compute.task == \
        "matmul"
    assert scenarios["paper-flight-moving"].compute.task == "linreg" and scenarios["range-sweep"].compute is None
    speeds = [i.p2 for i in scenarios["paper-flight-moving"].workers[0].mission.items if i.command == 178]
    assert speeds == [0.67]


@pytest.mark.parametrize("text, message", [
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n",
     "needs one [[vehicle]] with role \"master\" and at least one worker"),
    ("[[vehicle]]\nid = 'a'\nrole = 'master'\n", "missing key 'duration_s'"),
    ("duration_s = 'long'\n", "duration_s: expected a finite number, got 'long'"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'pilot'\n", "vehicle 1: role must be"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nmission = 'nope.plan'\n", "vehicle 1 (a): "),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[channel]\npreset = 'tin-can'\n", "[channel] channel 'tin-can'"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[[fault]]\nat_s = 5\nvehicle = 'c'\nkind = 'link_down'\n",
     "fault 1: no vehicle 'c'"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[[fault]]\nat_s = 5\nvehicle = 'a'\nkind = 'kill_worker'\n",
     "fault 1: kill_worker needs a worker of the MPI job"),
    ("duration_s = 10\n[compute\n", "not valid TOML"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[channel]\npreset = 'wifi-flight'\nbackground_airtime = 1.5\n",
     "background_airtime must be in [0, 1)"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[channel]\npreset = 'wifi-flight'\nretry_limit = 300\n",
     "retry_limit must be an integer in 0..255 (802.11's retry limit), got 300"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[channel]\npreset = 'wifi-flight'\nbackground_airtime = 0.2\n"
     "[network]\nair = 'medium'\n", "[channel] background_airtime = 0.2: the frame-level air"),
    (TWO + "[channel]\npreset = 'wifi-flight'\nmac_efficiency = 0.5\n[network]\nair = 'medium'\n",
     "[channel] mac_efficiency: the frame-level air"),
    (TWO + "[channel]\npreset = 'wifi-flight'\nmac = 'efficiency'\n[network]\nair = 'medium'\n",
     "[channel] mac: the frame-level air"),
    (TWO + "[network]\nair = 'medium'\nsharing = false\n", "[network]: sharing = false: on the frame-level air"),
    (TWO + "[network]\nqueue_packets = 50\n", "[network]: queue_packets: a station's transmit queue is the"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[channel]\npreset = 'wifi-flight'\nexponnent = 3\n",
     "unknown key exponnent"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[[fault]]\nat_s = 5\nvehicle = 'a'\nkind = 'gps_lost'\ncolour = 1\n",
     "unknown key fault.colour"),
    ("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\nid = 'b'\n"
     "role = 'worker'\nhome = [47, 8, 500]\n[compute]\ntask = 'sorting'\n",
     "compute.task must be one of linreg, linreg_gc, matmul, matmul_bpcc, matmul_mds"),
    # the examples (34): each a sentence naming the key and what was expected, never a traceback
    ("max_speedup = 'fast'\n" + TWO, "max_speedup: expected a finite number within [0.1, 1000] x real time, "
                                    "got 'fast'"),
    ("notes = 5\n" + TWO, "notes: expected a list of strings, got 5"),
    (TWO.replace("duration_s = 10\n", "duration_s = 10\nfault = [1]\n"), "fault: expected tables [[fault]]"),
    (TWO.replace("id = 'b'", "id = 'w/1'"), "vehicle 2: id (a directory and host name): expected an id of 1-32"),
    (TWO.replace("id = 'b'", "id = '<b>w</b>'"), "vehicle 2: id (a directory and host name): expected an id"),
    (TWO.replace("id = 'b'", "id = '..'"), "vehicle 2: id (a directory and host name): expected an id"),
    (TWO.replace("id = 'b'", f"id = '{'w' * 40}'"), "vehicle 2: id (a directory and host name): expected an id"),
    (TWO.replace("home = [47, 8, 500]", "home = [nan, 8, 500]", 1), "vehicle 1 (a): home[0] (latitude): expected "
                                                                     "a finite number within [-90, 90], got nan"),
    (TWO.replace("home = [47, 8, 500]", "home = [47, 181, 500]", 1), "home[1] (longitude): expected a finite number "
                                                                      "within [-180, 180], got 181"),
    (TWO + "[compute]\ntask = 'matmul'\niterations = -5\n", "compute.iterations: expected an integer within "
                                                             "[0, 10000000], got -5"),
    (TWO + "[[fault]]\nat_s = 5\nvehicle = 'b'\nkind = 'link_down'\nduration_s = -5\n",
     "fault 1: fault.duration_s: expected a finite number within [0, 604800] simulated s (0: until the end), got -5"),
    (TWO + "[[fault]]\nat_s = 50\nvehicle = 'b'\nkind = 'link_down'\n", "fault.at_s: expected a finite number "
                                                                         "within [0, 10] simulated s"),
    (TWO + "[[fault]]\nat_s = 5\nvehicle = 'b'\nkind = 'battery_pct'\nvalue = 150\n",
     "fault.value: expected a finite number within [0, 100] %"),
    (TWO + "[throughput]\ninterval_s = 0.001\n", "throughput.interval_s: expected a finite number within [0.05, "),
    ("max_speedup_x = 2\n" + TWO, "unknown key 'max_speedup_x' at the top level"),
    (TWO.replace("role = 'worker'", "role = 'worker'\ncolour = 'red'"), "vehicle 2: unknown key vehicle.colour"),
    ("compute = 5\n" + TWO, "compute: expected a table [compute]"),
    ("name = '../escape'\n" + TWO, "name (it names the run directory): expected an id"),
    (TWO.replace("duration_s = 10", "duration_s = inf"), "duration_s: expected a finite number"),
    (TWO + "[network]\nair = 'ether'\n", "air must be one of htb, medium, got 'ether'"),
    (TWO + "[network]\ncongestion_control = 'vegas'\n",
     "congestion_control must be one of cubic, reno, bbr, host, got 'vegas'"),
    (TWO + "[network]\nair = 'medium'\nqueue_packets = 0\n", "network.queue_packets: expected an integer within "
                                                               "[1, 100000], got 0"),
    (TWO + "[compute]\ntask = 'linreg'\ndevice = 'no-such-device.toml'\n",
     "[compute]: device: cannot read device profile"),
    (TWO + "[compute]\ntask = 'linreg'\ndevice = 'jetson-tx3'\n",
     "'jetson-tx3' is not a shipped profile's name (jetson-orin-nano, jetson-orin-nx, jetson-tx2, jetson-xavier-nx)"),
    (TWO + "[energy]\ncompanion = 'raspberry'\n", "[energy]: companion must be one of jetson-tx2, jetson-xavier-nx"),
    (TWO + "[energy]\ncompanion = ['jetson-tx2']\n", "energy.companion"),
    (TWO + "[energy]\ncompanion_mah = -1300\n", "energy.companion_mah: expected a finite number within (0, 100000] "
                                                  "mAh, got -1300"),
    (TWO + "[energy]\ndc_dc_efficiency = 1.2\n", "energy.dc_dc_efficiency: expected a finite number within (0, 1]"),
    (TWO.replace("role = 'worker'", "role = 'worker'\ncompanion_mah = 0"),
     "vehicle 2 (b): companion_mah: expected a finite number within (0, 100000] mAh, got 0"),
    (TWO + "[params]\nNAC_FRAME = 7\n", "NAC_FRAME"),
    # codes the fleet cannot hold (issue 30): refused before anything starts
    (TWO + "[compute]\ntask = 'linreg_gc'\ncode_s = 1\n", "[compute] task linreg_gc with 1 workers: --code-s 1: "
                                                         "gradient coding with 1 workers tolerates 0 <= s < 1"),
    (TWO + "[compute]\ntask = 'matmul_mds'\ncode_k = 2\n", "a code needs k <= the 1 workers"),
    (TWO + "[compute]\ntask = 'linreg_gc'\ncode_s = -1\n", "compute.code_s: expected an integer within [0, 10000]"),
])
def test_bad_scenarios_name_the_file_and_the_key(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as err:
        load_scenario(str(path))
    assert str(path) in str(err.value) and message in str(err.value)


def test_a_scenario_overrides_its_channel_and_can_add_background_load(tmp_path):
    path = tmp_path / "busy.toml"
    path.write_text("duration_s = 10\n[[vehicle]]\nid = 'a'\nrole = 'master'\nhome = [47, 8, 500]\n[[vehicle]]\n"
                    "id = 'b'\nrole = 'worker'\nhome = [47, 8, 500]\n[channel]\npreset = 'wifi-flight'\n"
                    "background_airtime = 0.25\nrician_k_db = 'none'\n")
    radio = load_scenario(str(path)).channel
    wifi = PRESETS["wifi-flight"]
    assert radio.background_airtime == 0.25 and radio.rician_k_db is None and radio.exponent == wifi.exponent
    assert radio.capacity_bps(10.0) == pytest.approx(0.75 * wifi.capacity_bps(10.0))


def test_the_run_writes_its_radio_once_and_the_children_are_pointed_at_that_file(tmp_path):
    """The scenario's one radio model goes to the run directory once (with the replay table it names on the
    sleep network); the agents' and the MPI job's command lines name that file; the scenario is left alone."""
    import io

    import numpy as np

    from nac_onboard.agent.config import load_agent_config
    from nac_onboard.compute.options import options_from_argv
    from nac_onboard.radio.files import load_channel, load_replay
    from nac_onboard.radio.replay import ReplayLinks
    from sitl.experiment.commands import Ports, agent_config, compute_args, run_channel_path
    from sitl.experiment.runner import Experiment

    text = (SCENARIO_DIR / "paper-flight-static.toml").read_text().replace('mission = "', f'mission = "{SCENARIO_DIR}/')
    text = re.sub(r"^air = .*$", 'air = "htb"  # a replay needs the htb air', text, count=1, flags=re.M)
    path = tmp_path / "busy.toml"
    path.write_text(text.replace('preset = "wifi-flight"', 'preset = "wifi-flight"\nbackground_airtime = 0.25', 1))
    scenario = load_scenario(str(path))
    assert scenario.channel.background_airtime == 0.25
    replay = ReplayLinks("run-x", {("master", "w1"): (np.array([0.0, 10.0]), np.array([20e6, 10e6]))})
    for network, table in (("sleep", replay), ("kernel", replay), ("sleep", None)):
        run_dir = tmp_path / f"run-{network}-{table is not None}"
        experiment = Experiment(scenario, run_dir, 1.0, 14550, out=io.StringIO(), analyze=False,
                                network=(network, "test"), replay=table)
        experiment._write_channel()
        written = load_channel(str(run_channel_path(run_dir)))
        assert experiment.scenario is scenario and written == experiment.radio
        if network == "sleep" and table is not None:
            assert written.replay_file == str(run_dir / "config" / "replay.json")
            assert load_replay(written.replay_file).rate_bps("w1", "master", 5.0) == 15e6
        else:
            assert written == scenario.channel and not (run_dir / "config" / "replay.json").exists()
        args = compute_args(scenario, run_dir, Ports(14550), 10.0, kernel=network == "kernel")
        assert args[args.index("--channel") + 1] == str(run_channel_path(run_dir))
        assert options_from_argv(args).channel == experiment.radio, "what the MPI ranks load"
        if network == "kernel":
            assert args[args.index("--pad-bits") + 1] == f"{scenario.channel.overhead_bits:g}"
        master = agent_config(scenario, 0, run_dir, Ports(14550), None if network == "sleep" else ["10.0.0.1"] * 3)
        emulated = f'emulate_channel = "{run_channel_path(run_dir)}"' if network == "sleep" else 'emulate_channel = ""'
        assert emulated in master
        if network == "sleep":
            (run_dir / "config" / "fleet.key").write_text("ab" * 32 + "\n")
            (run_dir / "config" / "master.toml").write_text(master)
            agent = load_agent_config(run_dir / "config" / "master.toml")
            assert agent.emulated_channel == experiment.radio, "what the master's agent loads for its probes"


def test_the_cli_refuses_bad_scenarios_and_speedups_with_exit_2(tmp_path, capsys):
    assert cli.main(["experiment", str(tmp_path / "missing.toml")]) == 2
    assert ("no such scenario file, nor a shipped scenario (coded-edge, energy-aware, energy-equal, "
            "paper-flight-moving") in capsys.readouterr().err
    assert cli.main(["experiment", "range-sweep", "--speedup", "5"]) == 2
    assert "--speedup 5 is outside what this scenario allows (up to 1x" in capsys.readouterr().err
    assert cli.main(["experiment", "paper-flight-moving", "--speedup", "9"]) == 2
    err = capsys.readouterr().err  # the notes' paragraphs of measurements named, not quoted whole
    assert "(up to 8x: its max_speedup, why in its notes (" in err and len(err) < 300, err
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "experiment.json").write_text("{}\n")  # a run there already: appended to, logs would mix
    assert cli.main(["experiment", "range-sweep", "--network", "sleep", "--out", str(tmp_path / "old")]) == 2
    assert "old: holds a run already (experiment.json): give another --out" in capsys.readouterr().err
    assert (tmp_path / "old" / "experiment.json").read_text() == "{}\n"


def test_a_mission_that_is_not_a_regular_bounded_file_is_refused_naming_the_vehicle(tmp_path):
    fifo = tmp_path / "fifo.plan"
    os.mkfifo(fifo)
    huge = tmp_path / "huge.plan"
    with open(huge, "wb") as f:
        f.truncate(2 * 1024 ** 3)  # sparse: refused by its size, never read
    for mission, words in ((fifo, "not a regular file"), ("/dev/zero", "not a regular file"),
                           (tmp_path, "not a regular file"), (huge, "2147483648 bytes; a mission file may have")):
        path = tmp_path / "bad.toml"
        path.write_text(TWO.replace("home = [47, 8, 500]\n[[vehicle]]", f"mission = '{mission}'\n[[vehicle]]"))
        with pytest.raises(ScenarioError) as err:
            load_scenario(str(path))
        assert f"vehicle 1 (a): {mission}" in str(err.value) and words in str(err.value)


def test_experiment_speedups_below_the_floor_are_refused_not_taken_as_real_time(tmp_path, capsys):
    """--speedup 0 used to fall back to the scenario's default (1x) and 1e-300 was taken."""
    for speedup in ("0", "1e-300", "nan", "-1"):
        with pytest.raises(SystemExit) as exit_:
            cli.main(["experiment", "range-sweep", f"--speedup={speedup}"])
        assert exit_.value.code == 2
        assert "argument --speedup: expected a finite number within [0.1, 1000]" in capsys.readouterr().err


def test_iperf3_probes_need_the_kernel_network(tmp_path):
    """On loopback iperf3 cannot be paced to the channel: refused before anything starts, with the reason."""
    import io

    from sitl.experiment.runner import Experiment, Outcome

    text = (SCENARIO_DIR / "paper-flight-static.toml").read_text().replace('mission = "', f'mission = "{SCENARIO_DIR}/')
    path = tmp_path / "iperf3.toml"
    path.write_text(text.replace("interval_s = 0.1", 'interval_s = 0.1\ntool = "iperf3"'))
    scenario = load_scenario(str(path))
    assert scenario.throughput.tool == "iperf3"
    result = Experiment(scenario, tmp_path / "run", 1.0, 14550, out=io.StringIO(), analyze=False,
                        network=("sleep", "asked for")).run()
    assert result.outcome is Outcome.BAD_INPUT and "needs the kernel network" in result.detail


def test_a_southern_or_western_home_is_taken_as_typed():
    from sitl.cli import build_parser, config_from_args, joined_coordinates

    argv = joined_coordinates(["run", "--home", "-35.363261,149.165230,584", "--ground-station", "-35.36,-1.5,580"])
    args = build_parser().parse_args(argv)
    config = config_from_args(args)
    assert (config.home.lat_deg, config.home.lon_deg, config.home.alt_m) == (-35.363261, 149.16523, 584.0)
    assert args.ground_station.lon_deg == -1.5
    assert joined_coordinates(["run", "--speedup", "-1"]) == ["run", "--speedup", "-1"], "only coordinates"


def test_a_scenarios_params_reach_every_vehicle_and_bad_ones_are_named(tmp_path):
    from sitl.experiment.scenario import ScenarioError, load_scenario

    assert dict(load_scenario("paper-flight-moving").params) == {"NAC_NAV_LAW": 1.0}, "the research's law"
    text = (SCENARIO_DIR / "paper-sim-static.toml").read_text()
    for table, words in (('[params]\nNO_SUCH = 1\n', "NO_SUCH: no such parameter"),
                         ('[params]\nWPNAV_SPEED = "fast"\n', "WPNAV_SPEED = 'fast': expected a number")):
        path = tmp_path / "bad.toml"
        path.write_text(text.replace("[params]\nNAC_NAV_LAW = 1", table.strip()).replace("../", str(SCENARIO_DIR) + "/")
                        .replace('mission = "', f'mission = "{SCENARIO_DIR}/'))
        with pytest.raises(ScenarioError, match=words):
            load_scenario(str(path))


def test_a_scenarios_device_profile_is_checked_and_reaches_the_ranks(tmp_path):
    (tmp_path / "tx2.toml").write_text('[device]\nname = "tx2"\nslowdown = 2000\nsource = "s"\n')
    path = tmp_path / "s.toml"
    path.write_text(TWO + "[compute]\ntask = 'linreg'\ndevice = 'tx2.toml'\n")
    with pytest.raises(ScenarioError, match=r"tx2.toml: \[device\] slowdown: expected a number in 1..1000"):
        load_scenario(str(path))
    (tmp_path / "tx2.toml").write_text('[device]\nname = "tx2"\nslowdown = 6\nsource = "s"\n')
    scenario = load_scenario(str(path))
    assert scenario.compute.device == str((tmp_path / "tx2.toml").resolve())
    args = compute_args(scenario, tmp_path / "run", Ports(47000), 100.0)
    assert args[args.index("--device") + 1] == scenario.compute.device


def test_the_kernel_networks_mpi_job_has_ucxs_keepalive_on_the_simulated_clock(tmp_path):
    """UCX resets a connection whose peer is silent 10 + 9 x 2 of its seconds; on the wall clock at 0.1x that is
    1.8 simulated s, less than a full queue holds, and the job lost its master. Below 1x both timers stretch;
    above it they stay UCX's (a loaded host's floor), never shorter."""
    path = tmp_path / "s.toml"
    path.write_text(TWO + "[compute]\ntask = 'linreg'\n")
    scenario = load_scenario(str(path))
    stations = [types.SimpleNamespace(netns=f"ns-{i}", address=f"10.9.0.{i + 1}") for i in range(2)]
    air = types.SimpleNamespace(stations=stations, exec_prefix=lambda i: ["ip", "netns", "exec", stations[i].netns])

    def genv(speedup):
        command = kernel_mpi_command(scenario, tmp_path / "run", Ports(47000), 10.0, air, tmp_path / "c", speedup)
        return {command[i + 1]: command[i + 2] for i, part in enumerate(command) if part == "-genv"}

    assert {k: genv(0.1)[k] for k in ("UCX_TCP_KEEPIDLE", "UCX_TCP_KEEPINTVL")} == {
        "UCX_TCP_KEEPIDLE": "100s", "UCX_TCP_KEEPINTVL": "20s"}
    for speedup in (1.0, 4.0):
        assert (genv(speedup)["UCX_TCP_KEEPIDLE"], genv(speedup)["UCX_TCP_KEEPINTVL"]) == ("10s", "2s")


def test_a_shipped_jetson_profile_is_named_in_a_scenario_and_a_file_of_that_name_comes_first(tmp_path, monkeypatch):
    """`device = 'jetson-tx2'` is the shipped profile (the ranks get its file) unless the scenario's folder holds a
    file of that name; its slowdown is this host's CPU score over the TX2's."""
    from nac_onboard.compute.device import SHIPPED, load_device_profile

    monkeypatch.setenv("NAC_HOST_CPU_SCORE", "3954")
    path = tmp_path / "s.toml"
    path.write_text(TWO + "[compute]\ntask = 'linreg'\ndevice = 'jetson-tx2'\n")
    scenario = load_scenario(str(path))
    assert scenario.compute.device == str((SHIPPED / "jetson-tx2.toml").resolve())
    assert load_device_profile(scenario.compute.device).slowdown == pytest.approx(2.0)
    (tmp_path / "jetson-tx2").write_text('[device]\nname = "ours"\nslowdown = 3\nsource = "our bench"\n')
    assert load_scenario(str(path)).compute.device == str((tmp_path / "jetson-tx2").resolve())


def test_a_device_profile_sets_how_fast_the_scenario_may_run_below_1x_with_too_few_cores(tmp_path, capsys,
                                                                                         monkeypatch):
    """On a host of 2 cores, a companion 3 times slower than it: one worker may run up to 3x (the file's 10 is
    lowered, and its default with it) and the CLI refuses 4x naming the companion; 15 workers up to 3 x 2 / 15 =
    0.4x (time dilation); 40 workers would need 0.15x... and at 1.2 times slower 0.06x, under the simulator's
    0.1x: refused, saying why. Ranks on "host" set no limit."""
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    (tmp_path / "slow.toml").write_text('[device]\nname = "slow"\nslowdown = 3\nsource = "s"\n')
    path = tmp_path / "s.toml"
    one = "max_speedup = 10\ndefault_speedup = 8\n" + TWO + "[compute]\ntask = 'linreg'\ndevice = 'slow.toml'\n"
    path.write_text(one)
    scenario = load_scenario(str(path))
    assert (scenario.max_speedup, scenario.default_speedup) == (3.0, 3.0)
    assert "a's companion (slow) computes 3 times slower than this host" in scenario.device_limit
    assert cli.main(["experiment", str(path), "--speedup", "4"]) == 2
    assert "--speedup 4 is outside what this scenario allows (up to 3x: a's companion (slow)" in \
        capsys.readouterr().err

    def fleet(workers: int) -> str:
        return one.replace("[compute]", "".join(f"[[vehicle]]\nid = 'w{k}'\nrole = 'worker'\nhome = [47, 8, 500]\n"
                                                for k in range(workers - 1)) + "[compute]")
    path.write_text(fleet(15))
    scenario = load_scenario(str(path))
    assert scenario.max_speedup == pytest.approx(0.4) and scenario.default_speedup == pytest.approx(0.4)
    assert "and 15 workers share this host's 2 cores" in scenario.device_limit
    (tmp_path / "slow.toml").write_text('[device]\nname = "slow"\nslowdown = 1.91958\nsource = "s"\n')
    path.write_text(fleet(4))  # 1.91958 x 2 / 4 = 0.9598: written as a user would, and never above it
    scenario = load_scenario(str(path))
    assert (scenario.max_speedup, scenario.default_speedup) == (0.95, 0.95), scenario.device_limit
    assert "so above 0.95x its work" in scenario.device_limit
    (tmp_path / "slow.toml").write_text('[device]\nname = "slow"\nslowdown = 1.2\nsource = "s"\n')
    path.write_text(fleet(40))
    with pytest.raises(ScenarioError, match=r"this host cannot run it: .* 40 workers share this host's 2 cores, so "
                                            r"above 0.06x .* the simulator runs at 0.1x or faster"):
        load_scenario(str(path))
    path.write_text(fleet(40).replace("device = 'slow.toml'", "device = 'host'"))
    scenario = load_scenario(str(path))
    assert (scenario.max_speedup, scenario.default_speedup, scenario.device_limit) == (10.0, 8.0, "")


def test_one_companions_own_device_and_the_allocation_keys_reach_the_ranks(tmp_path):
    """[[vehicle]] device gives that companion its own profile (checked now, named by the vehicle), and [compute]'s
    BPCC and re-planning keys reach the job's options: the options the ranks parse hold them all."""
    from nac_onboard.compute.options import options_from_argv
    from nac_onboard.radio.files import save_channel
    from sitl.experiment.commands import run_channel_path

    path = tmp_path / "s.toml"
    (tmp_path / "slow.toml").write_text('[device]\nname = "slow"\nslowdown = 0.5\nsource = "s"\n')
    text = TWO.replace("role = 'worker'", "role = 'worker'\ndevice = 'slow.toml'") + (
        "[compute]\ntask = 'matmul_bpcc'\nallocation = 'speed'\nreplan_every = 5\ncode_redundancy = 2.0\n"
        "batch_units = 2\nlink_rates = 'probes'\n")
    path.write_text(text)
    with pytest.raises(ScenarioError, match=r"\(b\): device: .*slow.toml: \[device\] slowdown: expected"):
        load_scenario(str(path))
    (tmp_path / "slow.toml").write_text('[device]\nname = "slow"\nslowdown = 20\nsource = "s"\n')
    scenario = load_scenario(str(path))
    assert scenario.workers[0].device == str((tmp_path / "slow.toml").resolve())
    args = compute_args(scenario, tmp_path / "run", Ports(47000), 100.0)
    run_channel_path(tmp_path / "run").parent.mkdir(parents=True)
    save_channel(scenario.channel, run_channel_path(tmp_path / "run"))  # what the runner writes for the ranks
    options = options_from_argv(args)
    assert options.device_for(1).name == "slow" and options.device_for(0).name == "host"
    assert (options.allocation, options.replan_every, options.code_redundancy, options.batch_units,
            options.link_rates) == ("speed", 5, 2.0, 2, "probes")
    path.write_text(text.replace("'probes'", "'guess'"))
    with pytest.raises(ScenarioError, match="compute.link_rates must be one of model, probes"):
        load_scenario(str(path))


def test_energy_allocation_hands_the_job_each_workers_companion_pack_as_rated(tmp_path):
    from nac_onboard.compute.options import options_from_argv
    from nac_onboard.radio.files import save_channel
    from sitl.experiment.commands import run_channel_path

    path = tmp_path / "energy.toml"
    path.write_text(TWO.replace("role = 'worker'", "role = 'worker'\ncompanion_mah = 500")
                    + "[[vehicle]]\nid = 'c'\nrole = 'worker'\nhome = [47, 8, 500]\n[compute]\ntask = 'linreg'\n"
                    "allocation = 'energy'\n[energy]\ncompanion_mah = 2000\n")
    scenario = load_scenario(str(path))
    run_channel_path(tmp_path / "run").parent.mkdir(parents=True)
    save_channel(scenario.channel, run_channel_path(tmp_path / "run"))  # what the runner writes for the ranks
    options = options_from_argv(compute_args(scenario, tmp_path / "run", Ports(14550), 10.0))
    assert options.allocation == "energy" and options.energy_wh == (4 * 3.7 * 0.5, 4 * 3.7 * 2.0)


def test_the_energy_companion_takes_the_device_profiles_names_and_follows_the_compute_device(tmp_path):
    """One companion, one name: [energy] takes the device profiles' names (the short ones as aliases), and left
    unset it is [compute]'s device where that is a shipped Jetson, so the two models do not describe two computers."""
    path = tmp_path / "e.toml"
    for energy, device, expected in ((None, "jetson-orin-nano", "jetson-orin-nano"), ("xavier-nx", None,
                                     "jetson-xavier-nx"), ("jetson-tx2", "jetson-orin-nx", "jetson-tx2"),
                                     (None, "host", "jetson-tx2"), (None, None, "jetson-tx2")):
        text = TWO + "[compute]\ntask = 'linreg'\n" + (f"device = '{device}'\n" if device else "")
        path.write_text(text + (f"[energy]\ncompanion = '{energy}'\n" if energy else ""))
        assert load_scenario(str(path)).energy.companion == expected, (energy, device)


GOOD_FRAME = {"name": "my-quad", "mass_kg": 1.6, "rotors": 4, "rotor_radius_m": 0.127, "blade_solidity": 0.1,
              "tip_speed_mps": 110.0, "profile_drag_coefficient": 0.012, "induced_correction": 0.1,
              "drag_area_m2": 0.012, "drive_efficiency": 0.8, "avionics_w": 4.0, "source": "our bench, 2026-11"}


def frame_file(path, **changes) -> str:
    fields = {**GOOD_FRAME, **changes}
    path.write_text("[frame]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in fields.items() if v is not None))
    return path.name


@pytest.mark.parametrize(("changes", "said"), [
    ({"mass_kg": -2.5}, "[frame] mass_kg = -2.5: expected 0.05..100"),
    ({"drive_efficiency": 1.2}, "[frame] drive_efficiency = 1.2: expected 0.05..1"),
    ({"rotors": 2.5}, "[frame] rotors = 2.5: expected a whole number"),
    ({"tip_speed_mps": "fast"}, "[frame] tip_speed_mps = 'fast': expected a number in 1..340"),
    ({"avionics_w": None}, "[frame] avionics_w: missing (every field is needed"),
    ({"colour": "red"}, "[frame] unknown field 'colour'"),
    ({"source": ""}, "[frame] source: expected a non-empty string"),
])
def test_a_frame_file_out_of_physical_range_is_refused_naming_file_field_and_range(tmp_path, changes, said):
    name = frame_file(tmp_path / "quad.toml", **changes)
    (tmp_path / "s.toml").write_text(TWO + f"[energy]\nframe = '{name}'\n")
    with pytest.raises(ScenarioError) as err:
        load_scenario(str(tmp_path / "s.toml"))
    assert str(err.value).startswith(f"{tmp_path / 'quad.toml'}: {said}"), str(err.value)


def test_a_frame_file_flies_every_vehicle_of_the_scenario(tmp_path):
    from sitl.vehicle import energy
    from sitl.vehicle.world import World

    (tmp_path / "s.toml").write_text(TWO + f"[energy]\nframe = '{frame_file(tmp_path / 'quad.toml')}'\n")
    scenario = load_scenario(str(tmp_path / "s.toml"))
    assert scenario.frame == energy.Frame(**GOOD_FRAME)
    world = World([v.home for v in scenario.vehicles], frames=(scenario.frame,) * 2)
    hover_w = float(energy.level_power_w(scenario.frame, 0.0))
    assert world.physics.power.induced_power_w[1] == pytest.approx(scenario.frame.induced_power_w)
    assert float(energy.level_power_w(world.physics.power, 0.0)[0]) == pytest.approx(hover_w)


def test_on_the_frame_level_air_agents_broadcast_their_state_and_probe_from_the_go(tmp_path):
    """On the medium air each agent sends its state as one broadcast to the run's /16 and listens on one port for
    everyone's (the fleet's default; a unicast to each peer was 900 frames a second from 16 vehicles); the htb air
    keeps a unicast to each peer, as its nftables drops are per pair. With a job the master's probes start at the
    go the job computes from."""
    import dataclasses

    import tomllib

    from nac_onboard.records import kinds
    from sitl.experiment.commands import agent_config

    addresses = ["10.70.0.1", "10.70.0.2", "10.70.0.3"]
    scenario = load_scenario("paper-flight-moving")
    configs = [tomllib.loads(agent_config(scenario, i, tmp_path, Ports(14550), addresses)) for i in range(3)]
    assert {c["peers"]["listen"] for c in configs} == {f"0.0.0.0:{Ports(14550).peers(0)}"}
    assert all(c["peers"]["send_to"] == [f"10.70.255.255:{Ports(14550).peers(0)}"] for c in configs)
    assert configs[0]["throughput"]["start_file"] == str(kinds.START_FILE.at(tmp_path))
    static = load_scenario("paper-flight-static")
    htb = dataclasses.replace(static, network=dataclasses.replace(static.network, air="htb"))
    master = tomllib.loads(agent_config(htb, 0, tmp_path, Ports(14550), addresses))
    assert master["peers"]["send_to"] == [f"10.70.0.2:{Ports(14550).peers(1)}", f"10.70.0.3:{Ports(14550).peers(2)}"]
