"""Bad input is a clear error, never a traceback or a hang (issue 34, acceptance 2).

Generated invalid values, one field at a time, in scenario files, agent configs and command-line arguments (wrong
types, NaN and infinities, out of range, bad ids, unknown keys and sections), each run through the real CLI's
main(argv) in process: exit 2, no traceback, and a sentence on stderr naming the file and the field. Files that
are not regular files (a FIFO with no writer, /dev/zero, a directory) or are huge (a 2 GB sparse file) go through
the CLIs as subprocesses, all at once, each under a timeout: no hang, exit 2 naming the file.

Every case is invalid by construction, so nothing may start: the entry points that would start something (the
experiment runner, the agent daemon, the simulator's serving loop) are replaced by a tripwire that fails the test
if reached, so a check that let a bad value through shows as that failure instead of as a run.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from unittest import mock

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ground import cli as ground_cli
from nac_onboard import cli as onboard_cli
from nac_onboard.compute import options as compute_options
from nac_onboard.inputs import is_name
from sitl import cli as sitl_cli
from sitl.experiment.scenario import TOP_KEYS, VEHICLE_KEYS

REPO = Path(__file__).resolve().parents[2]
FUZZ = settings(max_examples=60, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
_serial = itertools.count()

# ---------------------------------------------------------------------------------------------------- strategies

TEXT = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=12)
WRONG_TYPES = st.one_of(TEXT, st.booleans(), st.lists(st.integers(0, 3), max_size=2), st.just({"x": 1}))
NON_FINITE = st.sampled_from([math.nan, math.inf, -math.inf])
ID_CHARS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-"
BAD_IDS = st.one_of(
    st.sampled_from(["", ".", "..", "../x", "a/b", "../../etc", "<b>m</b>", "uav 1", "é", "a" * 33, "x" * 40]),
    TEXT.filter(lambda s: not (1 <= len(s) <= 32 and all(c in ID_CHARS for c in s)) or s in (".", "..")),
    st.text(alphabet=ID_CHARS, min_size=33, max_size=50))
BAD_NAMES = (BAD_IDS | st.just("y" * 129)).filter(lambda s: not is_name(s))  # a run's name: up to 128 characters


def bad_number(low: float | None, high: float | None, *, integer: bool = False, low_open: bool = False):
    """Anything a field of that range must refuse: wrong types, non-finite, below, above, non-integral."""
    options = [WRONG_TYPES, NON_FINITE]
    if integer:
        if low is not None:
            options.append(st.integers(min_value=-2**62, max_value=int(low) - 1))
        if high is not None:
            options.append(st.integers(min_value=int(high) + 1, max_value=2**62))
        options.append(st.integers(-10**6, 10**6).map(lambda k: k + 0.5))
    else:
        if low is not None:
            options.append(st.floats(max_value=low, exclude_max=not low_open, allow_nan=False, allow_infinity=False))
        if high is not None:
            options.append(st.floats(min_value=high, exclude_min=True, allow_nan=False, allow_infinity=False))
    return st.one_of(*options)


def arg_text(value) -> str:
    """A generated value as a command-line argument would carry it."""
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    return value if isinstance(value, str) else json.dumps(value)


def bad_arg(low, high, **kw):
    """On a command line every value is text: a wrong type drawn as text ("1") can be a valid number there."""
    drawn = bad_number(low, high, **kw).map(arg_text) | st.sampled_from(["", "fast", "1,2", "0x10", "1e999"])
    return drawn.filter(lambda text: not _valid_arg(text, low, high, **kw))


def bad_list_arg(low, high, **kw):
    """A comma-separated list of numbers: "1,2" is a valid one, so a drawn value must hold an item out of range."""
    return bad_arg(low, high, **kw).filter(
        lambda text: not all(_valid_arg(part, low, high, **kw) for part in text.split(",")))


def _valid_arg(text: str, low, high, *, integer: bool = False, low_open: bool = False) -> bool:
    """What the command line takes (nac_onboard.inputs.parse_number: int(text, 10) or float(text), in range)."""
    try:
        x = int(text, 10) if integer else float(text)
    except ValueError:
        return False
    return (math.isfinite(x) and (low is None or (x > low if low_open else x >= low))
            and (high is None or x <= high))

# ------------------------------------------------------------------------------------------------------ TOML out


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        # JSON's escapes are TOML's (non-ASCII left as UTF-8: JSON would escape astral characters as surrogate
        # pairs, which TOML refuses); TOML also refuses a raw DEL
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, list):
        return "[" + ", ".join(map(toml_value, v)) + "]"
    return "{" + ", ".join(f"{toml_value(str(k))} = {toml_value(x)}" for k, x in v.items()) + "}"


def toml_text(doc: dict) -> str:
    """Every key at the top level with an inline value: tables and arrays of tables included."""
    return "".join(f"{toml_value(str(k))} = {toml_value(v)}\n" for k, v in doc.items())


def with_value(doc: dict, path: tuple, value) -> dict:
    doc = json.loads(json.dumps(doc))  # a deep copy
    node = doc
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return doc


def write(tmp_path: Path, text: str, suffix: str = ".toml") -> Path:
    path = tmp_path / f"case-{next(_serial)}{suffix}"
    path.write_text(text, encoding="utf-8")
    return path


def call(main, argv: list[str]) -> tuple[int, str]:
    """main(argv) in this process: its exit code (argparse's SystemExit included) and what it wrote to stderr."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), _tripwires():
        try:
            code = main(argv)
        except SystemExit as exit_:
            code = exit_.code
    return code, err.getvalue()


def _started(*_args, **_kwargs):
    pytest.fail("invalid input got as far as starting something")


@contextlib.contextmanager
def _tripwires():
    with mock.patch("sitl.experiment.runner.run_scenario", _started), \
            mock.patch("nac_onboard.agent.daemon.run_agent", _started), mock.patch("sitl.cli.run", _started):
        yield


def assert_clear_error(code: int, err: str, *fragments: str) -> None:
    assert "Traceback" not in err and "internal error" not in err, err
    assert code == 2, (code, err)
    for fragment in fragments:
        assert fragment in err, (fragment, err)

# ---------------------------------------------------------------------------------------------------- scenarios


SCENARIO = {
    "name": "fuzz", "duration_s": 60, "max_speedup": 10, "default_speedup": 1, "notes": ["a note"],
    "vehicle": [{"id": "m", "role": "master", "home": [47.0, 8.0, 500.0]},
                {"id": "w1", "role": "worker", "home": [47.0001, 8.0, 500.0]}],
    "compute": {"task": "matmul", "iterations": 5, "timeout_s": 3.0},
    "throughput": {"period_s": 2.0, "duration_s": 0.5, "interval_s": 0.1},
    "network": {"period_s": 0.1},
    "params": {"WPNAV_SPEED": 500},
    "fault": [{"at_s": 10, "vehicle": "w1", "kind": "battery_pct", "duration_s": 5, "value": 20}],
}

SCENARIO_FIELDS = [  # (path, invalid values, fragments the message must hold)
    (("max_speedup",), bad_number(0.1, 1000), ["max_speedup"]),
    (("default_speedup",), bad_number(0.1, 10), ["default_speedup"]),
    (("duration_s",), bad_number(0, 7 * 86400, low_open=True), ["duration_s"]),
    (("name",), BAD_IDS, ["name"]),
    (("notes",), st.one_of(st.integers(), st.lists(st.integers(), min_size=1, max_size=3)), ["notes"]),
    (("description",), st.one_of(st.integers(), st.lists(TEXT, max_size=2)), ["description"]),
    (("vehicle", 1, "id"), BAD_IDS | st.integers(), ["vehicle 2: id"]),
    (("vehicle", 0, "role"), TEXT.filter(lambda s: s not in ("master", "worker")), ["vehicle 1: role"]),
    (("vehicle", 0, "home", 0), bad_number(-90, 90), ["vehicle 1 (m): home[0] (latitude)"]),
    (("vehicle", 1, "home", 1), bad_number(-180, 180), ["vehicle 2 (w1): home[1] (longitude)"]),
    (("vehicle", 1, "home", 2), bad_number(-500, 10_000), ["vehicle 2 (w1): home[2] (altitude m)"]),
    (("compute", "iterations"), bad_number(0, 10_000_000, integer=True), ["compute.iterations"]),
    (("compute", "timeout_s"), bad_number(0, 3600, low_open=True), ["compute.timeout_s"]),
    (("compute", "task"), TEXT.filter(lambda s: s not in ("matmul", "linreg")), ["compute.task"]),
    (("throughput", "period_s"), bad_number(0, 3600, low_open=True), ["throughput.period_s"]),
    (("throughput", "interval_s"), bad_number(0.05, 3600), ["throughput.interval_s"]),
    (("network", "period_s"), bad_number(0.01, 10), ["network", "period_s"]),
    (("params", "WPNAV_SPEED"), bad_number(20, 2000), ["[params]", "WPNAV_SPEED"]),
    (("fault", 0, "at_s"), bad_number(0, 60), ["fault 1: fault.at_s"]),
    (("fault", 0, "duration_s"), bad_number(0, 7 * 86400), ["fault 1: fault.duration_s"]),
    (("fault", 0, "value"), bad_number(0, 100), ["fault 1: fault.value"]),
    (("fault",), st.one_of(st.integers(), st.lists(st.integers(), min_size=1, max_size=2)), ["fault"]),
    (("compute",), st.one_of(st.integers(), TEXT, st.lists(st.integers(), max_size=2)), ["compute"]),
    (("vehicle",), st.one_of(st.integers(), TEXT), ["vehicle"]),
]
KEYS = st.text(alphabet=ID_CHARS, min_size=1, max_size=12)
UNKNOWN_KEYS = [  # (table path, keys it knows, fragment before the key)
    ((), TOP_KEYS, ""), (("compute",), ("task", "iterations", "timeout_s", "on_missing", "allocation", "args"),
                         "compute."),
    (("vehicle", 0), VEHICLE_KEYS, "vehicle."), (("fault", 0), ("at_s", "vehicle", "kind", "duration_s", "value"),
                                                 "fault."),
    (("throughput",), ("period_s", "duration_s", "interval_s", "tool"), "throughput."),
    (("network",), ("period_s", "sharing"), "network."),
]


@st.composite
def scenario_cases(draw):
    if draw(st.booleans()):
        path, values, fragments = draw(st.sampled_from(SCENARIO_FIELDS))
        return with_value(SCENARIO, path, draw(values)), fragments
    table, known, prefix = draw(st.sampled_from(UNKNOWN_KEYS))
    key = draw(KEYS.filter(lambda k: k not in known))
    return with_value(SCENARIO, (*table, key), 1), [f"{prefix}{key}"]


def test_the_base_scenario_is_valid(tmp_path):
    """The fuzz below breaks one field of this: it must load as it is, else every case would fail for it."""
    from sitl.experiment.scenario import load_scenario

    scenario = load_scenario(str(write(tmp_path, toml_text(SCENARIO))))
    assert [v.id for v in scenario.vehicles] == ["m", "w1"] and scenario.faults[0].value == 20


@FUZZ
@given(case=scenario_cases())
def test_every_invalid_scenario_field_is_exit_2_naming_file_and_field(tmp_path, case):
    doc, fragments = case
    path = write(tmp_path, toml_text(doc))
    code, err = call(sitl_cli.main, ["experiment", str(path)])
    assert_clear_error(code, err, str(path), *fragments)


def test_too_many_vehicles_for_the_ports_is_refused(tmp_path):
    vehicles = [{"id": f"v{k}", "role": "worker", "home": [47.0, 8.0, 500.0]} for k in range(6600)]
    vehicles[0]["role"] = "master"
    path = write(tmp_path, toml_text({**SCENARIO, "vehicle": vehicles, "fault": []}))
    assert_clear_error(*call(sitl_cli.main, ["experiment", str(path)]), str(path), "at most 250 vehicles")
    path = write(tmp_path, toml_text(SCENARIO))
    assert_clear_error(*call(sitl_cli.main, ["experiment", str(path), "--base-port", "65530"]),
                       "--base-port 65530", "beyond 65535")

# ----------------------------------------------------------------------------------------------- agent configs


AGENT = {"vehicle": {"id": "uav1", "role": "worker"}, "peers": {"allow_unsigned": True}}
AGENT_FIELDS = [
    (("vehicle", "id"), BAD_IDS | st.integers(), "vehicle.id"),
    (("vehicle", "role"), TEXT.filter(lambda s: s not in ("master", "worker")), "vehicle.role"),
    (("vehicle", "sysid"), bad_number(0, 255, integer=True), "vehicle.sysid"),
    (("autopilot", "stream_hz"), bad_number(0, 1000), "autopilot.stream_hz"),
    (("autopilot", "link_timeout_s"), bad_number(0.1, 3600), "autopilot.link_timeout_s"),
    (("log", "run_id"), BAD_NAMES.filter(bool), "log.run_id"),
    (("log", "telemetry_hz"), bad_number(0.01, 1000), "log.telemetry_hz"),
    (("peers", "rate_hz"), bad_number(0.01, 1000), "peers.rate_hz"),
    (("peers", "max_peers"), bad_number(1, 100_000, integer=True), "peers.max_peers"),
    (("throughput", "port"), bad_number(1, 65535, integer=True), "throughput.port"),
    (("throughput", "interval_s"), bad_number(0.05, 3600), "throughput.interval_s"),
    (("throughput", "bytes"), bad_number(0, 2**40, integer=True), "throughput.bytes"),
    (("throughput", "rate_bps"), bad_number(0, 1e12), "throughput.rate_bps"),
]
SECTIONS = ("vehicle", "autopilot", "log", "routing", "peers", "state_feed", "throughput")


@st.composite
def agent_cases(draw):
    choice = draw(st.integers(0, 2))
    if choice == 0:
        path, values, field = draw(st.sampled_from(AGENT_FIELDS))
        section = {**AGENT.get(path[0], {})}
        return {**AGENT, path[0]: {**section, path[1]: draw(values)}}, field
    if choice == 1:
        section = draw(st.sampled_from(SECTIONS))
        key = draw(KEYS.filter(lambda k: k not in ("id", "role", "sysid", "allow_unsigned")))
        return {**AGENT, section: {**AGENT.get(section, {}), key: 1}}, f"{section}.{key}"
    section = draw(KEYS.filter(lambda k: k not in SECTIONS))
    return {**AGENT, section: {"x": 1}}, f"[{section}]"


@FUZZ
@given(case=agent_cases())
def test_every_invalid_agent_config_field_is_exit_2_naming_file_and_field(tmp_path, case):
    doc, field = case
    path = write(tmp_path, toml_text(doc))
    code, err = call(onboard_cli.main, ["agent", "--config", str(path)])
    assert_clear_error(code, err, str(path), field)

# ------------------------------------------------------------------------------------------ command-line options


CLI_CASES = [  # (main, argv before the value, option, invalid values, fragment)
    (sitl_cli.main, ["run"], "--speedup", bad_arg(0.1, 1000), "--speedup"),
    (sitl_cli.main, ["run"], "--spacing-m", bad_arg(0, 10_000), "--spacing-m"),
    (sitl_cli.main, ["run"], "--vehicles", bad_arg(1, 250, integer=True), "--vehicles"),
    (sitl_cli.main, ["run"], "--seed", bad_arg(0, 2**32 - 1, integer=True), "--seed"),
    (sitl_cli.main, ["run"], "--gcs-base-port", bad_arg(1, 65535, integer=True), "--gcs-base-port"),
    # bad_arg: a drawn text that reads as a number in range ("0") would make a valid home
    (sitl_cli.main, ["run"], "--home", bad_arg(-90, 90).map(lambda v: f"{v},8.5,400"), "--home"),
    (sitl_cli.main, ["run"], "--home", bad_arg(-500, 10_000).map(lambda v: f"47,8.5,{v}"), "--home"),
    (sitl_cli.main, ["experiment", "paper-sim-static"], "--speedup", bad_arg(0.1, 1000), "--speedup"),
    (sitl_cli.main, ["experiment", "paper-sim-static"], "--base-port", bad_arg(1024, 65535, integer=True),
     "--base-port"),
    (sitl_cli.main, ["radio", "paper-sim"], "--draws", bad_arg(10, 100_000, integer=True), "--draws"),
    (sitl_cli.main, ["radio", "paper-sim"], "--distances-m", bad_list_arg(0, 1e6, low_open=True), "--distances-m"),
    (compute_options.parse_args, ["--task", "linreg"], "--iterations", bad_arg(1, 1e7, integer=True),
     "--iterations"),
    (compute_options.parse_args, ["--task", "linreg"], "--duration-s", bad_arg(0, 7 * 86400, low_open=True),
     "--duration-s"),
    (compute_options.parse_args, ["--task", "linreg"], "--learning-rate", bad_arg(0, 1000, low_open=True),
     "--learning-rate"),
    (compute_options.parse_args, ["--task", "linreg"], "--timeout-s", bad_arg(0, 86400, low_open=True),
     "--timeout-s"),
    (compute_options.parse_args, ["--task", "matmul"], "--m", bad_arg(1, 1e7, integer=True), "--m"),
    (compute_options.parse_args, ["--task", "linreg"], "--vehicles", BAD_IDS.filter(bool), "--vehicles"),
    (ground_cli.main, [], "--sysid", bad_arg(1, 255, integer=True), "--sysid"),
    (ground_cli.main, ["wait", "landed"], "--timeout-s", bad_arg(0, 86400, low_open=True), "--timeout-s"),
    (ground_cli.main, ["logs", "analyze", "."], "--bin-m", bad_arg(0.01, 10_000), "--bin-m"),
    (ground_cli.main, ["logs", "analyze", "."], "--master", BAD_IDS, "--master"),
    (onboard_cli.main, ["agent", "--config", "deploy/worker.toml"], "--run-id", BAD_NAMES, "--run-id"),
]


@st.composite
def cli_cases(draw):
    main, argv, option, values, fragment = draw(st.sampled_from(CLI_CASES))
    value = draw(values)
    argv = [*argv, f"{option}={value}"] if main is not ground_cli.main or argv else [f"{option}={value}", "arm"]
    return main, argv, fragment


@FUZZ
@given(case=cli_cases())
def test_every_invalid_option_is_exit_2_naming_the_option(case):
    main, argv, fragment = case
    code, err = call(main, argv)
    assert_clear_error(code, err, fragment)


@FUZZ
@given(value=bad_arg(0, 10_000, low_open=True))
def test_a_bad_positional_number_names_its_argument(value):
    assert_clear_error(*call(ground_cli.main, ["takeoff", "--", value]), "alt_m")

@FUZZ
@given(at=st.one_of(NON_FINITE, st.floats(max_value=0, exclude_max=True, allow_nan=False)) | st.just(0.0),
       d=st.one_of(NON_FINITE, st.floats(max_value=0, exclude_max=True, allow_nan=False),
                   st.floats(min_value=1e6, exclude_min=True, allow_nan=False, allow_infinity=False)))
def test_a_positions_script_with_non_finite_times_or_distances_is_refused_naming_it(tmp_path, at, d):
    """Every distance drawn is invalid (non-finite, negative or beyond 1,000 km), whatever the time."""
    path = write(tmp_path, json.dumps({"by": "time_s", "distances_m": {"1": [[at, d]]}}), ".json")
    code, err = call(compute_options.parse_args, ["--task", "linreg", "--positions", "script",
                                                  "--positions-script", str(path)])
    assert_clear_error(code, err, str(path), "positions script: rank 1", "expected a finite time >= 0")


# ------------------------------------------------------------------------ files that are not files: subprocesses


def test_fifos_devices_and_huge_files_are_refused_by_every_cli_without_hanging(tmp_path):
    """Each CLI as users start it, given a FIFO with no writer (which an unguarded read waits on forever),
    /dev/zero (which never ends), a directory or a 2 GB sparse file: all started at once, each must exit 2
    naming the file within its timeout."""
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)
    sparse = tmp_path / "huge.plan"
    with open(sparse, "wb") as f:
        f.truncate(2 * 1024 ** 3)
    run = tmp_path / "run"
    (run / "w1").mkdir(parents=True)
    os.mkfifo(run / "w1" / "agent.jsonl")

    def scenario_with_mission(mission) -> Path:
        doc = with_value(SCENARIO, ("vehicle", 1), {"id": "w1", "role": "worker", "mission": str(mission)})
        return write(tmp_path, toml_text(doc))

    py = [sys.executable, "-m"]
    cases = [
        ([*py, "sitl.cli", "experiment", str(fifo)], [str(fifo), "FIFO"]),
        ([*py, "sitl.cli", "experiment", str(scenario_with_mission("/dev/zero"))], ["vehicle 2 (w1)", "/dev/zero"]),
        ([*py, "sitl.cli", "experiment", str(scenario_with_mission(fifo))], ["vehicle 2 (w1)", str(fifo)]),
        ([*py, "sitl.cli", "experiment", str(scenario_with_mission(sparse))], ["vehicle 2 (w1)", "2147483648 bytes"]),
        ([*py, "sitl.cli", "run", "--params", str(fifo)], ["parameter file", str(fifo), "FIFO"]),
        ([*py, "sitl.cli", "run", "--params", "/dev/zero"], ["parameter file /dev/zero", "device"]),
        ([*py, "sitl.cli", "radio", str(fifo)], ["channel model", str(fifo)]),
        ([*py, "sitl.cli", "run", "--home", "nan,8.5,400"], ["--home", "latitude", "nan"]),
        ([*py, "sitl.cli", "run", "--spacing-m", "nan"], ["--spacing-m", "nan"]),
        ([*py, "nac_onboard.cli", "agent", "--config", str(fifo)], ["agent config", str(fifo), "FIFO"]),
        ([*py, "nac_onboard.cli", "agent", "--config", "/dev/zero"], ["agent config /dev/zero", "device"]),
        ([*py, "nac_onboard.cli", "log", "check", str(fifo), "/dev/zero", str(sparse)],
         [f"log {fifo}: is a FIFO", "log /dev/zero: is a device", f"log {sparse}: 2048.0 MiB"]),
        ([*py, "nac_onboard.compute", "--task", "linreg", "--iterations", "0"], ["--iterations"]),
        ([*py, "nac_onboard.compute", "--task", "linreg", "--positions", "script", "--positions-script", str(fifo)],
         ["--positions-script", str(fifo), "FIFO"]),
        ([*py, "ground.cli", "mission", "validate", str(fifo)], [str(fifo), "not a regular file"]),
        ([*py, "ground.cli", "mission", "validate", str(sparse)], [str(sparse), "bytes; a mission file may have"]),
        ([*py, "ground.cli", "logs", "analyze", str(run)], [f"log {run / 'w1' / 'agent.jsonl'}: is a FIFO"]),
    ]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    procs = [(subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env),
              argv, fragments) for argv, fragments in cases]
    try:
        for proc, argv, fragments in procs:
            _, err = proc.communicate(timeout=90)
            assert "Traceback" not in err, (argv, err)
            assert proc.returncode == 2, (argv, proc.returncode, err)
            for fragment in fragments:
                assert fragment in err, (argv, fragment, err)
    finally:
        for proc, _, _ in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
