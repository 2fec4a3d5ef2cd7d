"""nac_onboard/inputs.py, the checks every input edge shares: ids, finite numbers in range, files read whole only
when they are regular and within their size limit, names that stay in their directory."""

from __future__ import annotations

import argparse
import math
import os
import re
from dataclasses import dataclass

import pytest
from hypothesis import given
from hypothesis import strategies as st

from nac_onboard import inputs
from nac_onboard.errors import BadInput
from nac_onboard.inputs import (
    check_id,
    check_name,
    check_number,
    check_regular_file,
    inside,
    is_id,
    number_arg,
    parse_number,
    read_bounded,
    read_bounded_text,
)
from nac_onboard.tomlfile import ranged, read_toml, to_dataclass

ID_CHARS = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-"


@given(st.text(alphabet=ID_CHARS, min_size=1, max_size=32).filter(lambda s: s not in (".", "..")))
def test_every_id_of_the_pattern_is_taken(text):
    assert check_id(text, "vehicle.id") == text


@given(st.one_of(
    st.text(max_size=40).filter(lambda s: not re.fullmatch(r"[A-Za-z0-9._-]{1,32}", s)),
    st.text(alphabet=ID_CHARS, min_size=33, max_size=60),
    st.sampled_from([".", "..", "../x", "a/b", "<b>x</b>", "", "uav 1", "é", "a\x00b"]),
    st.integers(), st.none(), st.lists(st.text(max_size=3), max_size=2)))
def test_anything_else_is_refused_naming_the_field_and_the_rule(value):
    assert not is_id(value)
    with pytest.raises(BadInput) as err:
        check_id(value, "f.toml: vehicle.id")
    assert str(err.value).startswith("f.toml: vehicle.id: expected an id of 1-32 letters")


def test_a_runs_name_is_an_id_or_longer_but_never_leaves_its_directory():
    assert check_name("paper-flight-moving-20261125T135500", "log.run_id") == "paper-flight-moving-20261125T135500"
    assert check_name("r" * 128, "log.run_id")
    for bad in ("r" * 129, "..", ".", "", "a/b", "../runs", "run 1", 7):
        with pytest.raises(BadInput, match="log.run_id: expected a name of 1-128 letters"):
            check_name(bad, "log.run_id")


@given(st.floats(min_value=-5, max_value=5, allow_nan=False))
def test_a_number_in_range_comes_back_as_float(x):
    assert check_number(x, "k", -5, 5) == x and isinstance(check_number(x, "k", -5, 5), float)


@given(st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, True, False, "3", None, [1]]),
    st.floats(min_value=5, exclude_min=True), st.floats(max_value=-5, exclude_max=True)))
def test_non_finite_wrong_typed_or_out_of_range_numbers_name_the_field_and_range(value):
    with pytest.raises(BadInput) as err:
        check_number(value, "s.toml: max_speedup", -5, 5, unit="x")
    assert str(err.value).startswith("s.toml: max_speedup: expected a finite number within [-5, 5] x, got ")


def test_integers_and_open_bounds():
    assert check_number(3, "n", 1, 5, integer=True) == 3
    for bad in (1.5, 0, 6, True):
        with pytest.raises(BadInput, match=r"n: expected an integer within \[1, 5\]"):
            check_number(bad, "n", 1, 5, integer=True)
    with pytest.raises(BadInput, match=r"expected a finite number within \(0, 2\], got 0"):
        check_number(0, "speedup", 0, 2, low_open=True)
    assert parse_number("1e3", "x", 0, 1e4) == 1000.0
    for text in ("nan", "inf", "", "1,2", "0x10", "1e309"):
        with pytest.raises(BadInput, match="x: expected a finite number"):
            parse_number(text, "x", 0, 1e4)


def test_an_argparse_option_with_a_bad_number_exits_2_naming_the_option(capsys):
    parser = argparse.ArgumentParser(prog="p")
    parser.add_argument("--speedup", type=number_arg(0.1, 1000))
    assert parser.parse_args(["--speedup", "2"]).speedup == 2.0
    for text in ("0", "1e-300", "nan", "inf", "fast"):
        with pytest.raises(SystemExit) as exit_:
            parser.parse_args([f"--speedup={text}"])
        assert exit_.value.code == 2
        assert "argument --speedup: expected a finite number within [0.1, 1000]" in capsys.readouterr().err


def test_a_regular_file_is_read_whole(tmp_path):
    path = tmp_path / "a.toml"
    path.write_bytes(b"x" * 1000)
    assert read_bounded(path, "config", 1000) == b"x" * 1000
    path.write_bytes(b"\xef\xbb\xbfname = 1\n")
    assert read_bounded_text(path, "config") == "name = 1\n"
    path.write_bytes(b"\xff\xfe")
    with pytest.raises(BadInput, match=r"config .*a.toml: not UTF-8 text \(byte 0\)"):
        read_bounded_text(path, "config")


def test_a_fifo_a_device_a_directory_and_a_missing_file_are_refused_before_opening(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)  # no writer: opening it for reading without O_NONBLOCK would wait forever
    cases = {fifo: "is a FIFO", "/dev/zero": "is a device", tmp_path: "is a directory",
             tmp_path / "nope": "cannot read mission .*nope: No such file"}
    for path, message in cases.items():
        for read in (read_bounded, check_regular_file):
            with pytest.raises(BadInput, match=f"{message}"):
                read(path, "mission", inputs.MAX_CONFIG_BYTES)


def test_a_sparse_file_over_the_limit_is_refused_by_its_size_without_reading_it(tmp_path):
    path = tmp_path / "agent.jsonl"
    with open(path, "wb") as f:
        f.truncate(2 * 1024 ** 3)  # 2 GB, no blocks
    with pytest.raises(BadInput, match=r"log .*agent.jsonl: 2048.0 MiB; a log may have at most 256.0 MiB"):
        read_bounded(path, "log", inputs.MAX_LOG_BYTES)


def test_a_file_longer_than_its_stated_size_is_cut_at_the_limit():
    """/proc files state size 0 and hold more: the bounded read stops at the limit instead of trusting stat."""
    with pytest.raises(BadInput, match="grew past 16 bytes while read"):
        read_bounded("/proc/self/status", "status", 16)


def test_inside_keeps_names_in_their_directory(tmp_path):
    assert inside(tmp_path, "w1/agent.toml", "vehicle id") == tmp_path / "w1/agent.toml"
    (tmp_path / "out").symlink_to("/tmp")
    for name in ("..", "../x", "/etc/passwd", ".", "out/x", "a/../../b"):
        with pytest.raises(BadInput, match="vehicle id: .* leaves its directory"):
            inside(tmp_path, name, "vehicle id")


@dataclass(frozen=True)
class _Plan:
    period_s: float = ranged(1.0, 0.0, 10.0, low_open=True, unit="s")
    count: int = ranged(0, 0, 5)


def test_tomlfile_fields_with_a_range_are_refused_out_of_it(tmp_path):
    assert to_dataclass(_Plan, {"period_s": 2, "count": 5}, "p.toml") == _Plan(2.0, 5)
    with pytest.raises(BadInput, match=r"p.toml: plan.period_s: expected a finite number within \(0, 10\] s, got 0"):
        to_dataclass(_Plan, {"period_s": 0}, "p.toml", table="plan")
    with pytest.raises(BadInput, match=r"p.toml: plan.count: expected an integer within \[0, 5\], got -5"):
        to_dataclass(_Plan, {"count": -5}, "p.toml", table="plan")
    fifo = tmp_path / "c.toml"
    os.mkfifo(fifo)
    with pytest.raises(BadInput, match="agent config .*c.toml: is a FIFO; expected a regular file"):
        read_toml(fifo, "agent config")
