"""The run's records have one owner: nac_onboard/records. Its definitions check writers, make docs/records.md, and
no other source spells a run file's name or a record kind."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

from nac_onboard.flight_log import JsonlLog, RecordsVersionError, read_jsonl
from nac_onboard.records import READABLE_VERSIONS, SCHEMA_VERSION, kinds
from nac_onboard.records.schema import STRICT_ENV

REPO = Path(__file__).resolve().parents[2]
SOURCES = ("missions", "nac_onboard", "sitl", "ground", "benchmarks")
OWNER = REPO / "nac_onboard" / "records"
#: names with an extension (`start` and `hostfile` are ordinary words: their writers use the constants all the same)
FILE_NAMES = {f.name for f in kinds.FILES if "." in f.name and "VEHICLE" not in f.name and "-N." not in f.name}
KIND_NAMES = {k.name for k in kinds.KINDS}
#: kinds whose names are no ordinary word nor a MAVLink state's name: spelled anywhere outside the owner (but as a
#: key or an attribute's name), they are a kind spelled by hand
DISTINCT_KINDS = {name for name in KIND_NAMES if "_" in name} - {k.name for k in kinds.CHANGES.values()}
#: calls whose string arguments are kinds
KIND_CALLS = {"write", "of_kind", "last_record"}


def _docstrings(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) \
                and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
            ids.add(id(body[0].value))
    return ids


def _keys(tree: ast.AST) -> set[int]:
    """Strings used as a dict key (literal, subscript, .get) or getattr's name: a field's name, maybe a kind's."""
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Dict):
            ids.update(id(k) for k in node.keys if k is not None)
        elif isinstance(node, ast.Subscript):
            ids.add(id(node.slice))
        elif isinstance(node, ast.Call) and getattr(node.func, "id", None) in ("getattr", "hasattr", "setattr") \
                and len(node.args) > 1:
            ids.add(id(node.args[1]))
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", None) in ("get", "pop", "setdefault") \
                and node.args:
            ids.add(id(node.args[0]))
    return ids


def _strings(node: ast.AST) -> list[ast.Constant]:
    return [n for n in ast.walk(node) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def _is_kind_key(node: ast.AST) -> bool:
    """`r["kind"]` or `r.get("kind")`."""
    if isinstance(node, ast.Subscript):
        return isinstance(node.slice, ast.Constant) and node.slice.value == "kind"
    return isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get" \
        and bool(node.args) and isinstance(node.args[0], ast.Constant) and node.args[0].value == "kind"


def spelled_by_hand(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    docstrings, keys = _docstrings(tree), _keys(tree)
    found = []

    def flag(node: ast.Constant, what: str) -> None:
        found.append((node.lineno, node.col_offset, f"{path.relative_to(REPO)}:{node.lineno}: {what} {node.value!r}"))

    for node in _strings(tree):
        if id(node) in docstrings:
            continue
        text = node.value
        if any(text == name or text.endswith("/" + name) for name in FILE_NAMES) \
                or (text.startswith("rank-") and text.endswith(".jsonl")):
            flag(node, "run file name")
        elif text in DISTINCT_KINDS and id(node) not in keys:
            flag(node, "record kind")
    for node in ast.walk(tree):
        kind_strings: list[ast.Constant] = []
        if isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name)) \
                and getattr(node.func, "attr", getattr(node.func, "id", None)) in KIND_CALLS:
            kind_strings = [a for a in node.args if isinstance(a, ast.Constant)]
        elif isinstance(node, ast.Compare) and any(_is_kind_key(n) for n in (node.left, *node.comparators)):
            kind_strings = [s for n in (node.left, *node.comparators) for s in _strings(n)]
        elif isinstance(node, ast.Dict):
            keys = [k.value for k in node.keys if isinstance(k, ast.Constant)]
            if "kind" in keys:
                value = node.values[keys.index("kind")] if None not in node.keys else None
                kind_strings = [value] if isinstance(value, ast.Constant) else []
            elif sum(k in DISTINCT_KINDS for k in keys) >= 2:
                kind_strings = [k for k in node.keys if isinstance(k, ast.Constant)]
        for s in kind_strings:
            if isinstance(s.value, str) and s.value in KIND_NAMES:
                flag(s, "record kind")
    return [text for *_, text in sorted(set(found))]


def test_no_source_spells_a_run_file_or_a_record_kind_outside_the_records_module():
    found = []
    for folder in SOURCES:
        for path in sorted((REPO / folder).rglob("*.py")):
            if OWNER not in path.parents:
                found += spelled_by_hand(path)
    assert not found, "spelled outside nac_onboard/records/kinds.py:\n" + "\n".join(found)


def test_the_walk_finds_what_it_looks_for(tmp_path):
    """The detector itself: each way of spelling a name by hand is caught (else the test above proves nothing)."""
    sample = REPO / "tests" / "unit" / "_records_sample.py"
    sample.write_text('"""agent.jsonl in a docstring is prose."""\n'
                      'a = run / "compute" / "compute.jsonl"\n'
                      'log.write("iteration", x=1)\n'
                      'if r.get("kind") == "telemetry": pass\n'
                      'b = {"t_s": 0, "kind": "throughput"}\n'
                      'c = "run_summary"\n'
                      'd = {"link_lost": 1, "peer_seen": 2}\n'
                      'e = {"telemetry": 0, "routing_refused": 1, "mode": 2}\n'
                      'f = getattr(msg, "mission_state", 0)\n')
    try:
        found = spelled_by_hand(sample)
    finally:
        sample.unlink()
    assert [f.split(": ", 1)[1] for f in found] == [
        "run file name 'compute.jsonl'", "record kind 'iteration'", "record kind 'telemetry'",
        "record kind 'throughput'", "record kind 'run_summary'", "record kind 'link_lost'", "record kind 'peer_seen'"]


def test_docs_records_md_is_made_from_the_definitions():
    out = subprocess.run([sys.executable, "-m", "nac_onboard.records", "--check"], capture_output=True, text=True,
                         cwd=REPO, timeout=60)
    assert out.returncode == 0, out.stderr
    text = (REPO / "docs" / "records.md").read_text()
    for kind in kinds.KINDS:
        assert f"### `{kind.name}`" in text
        for field in kind.fields:
            assert f"| `{field.name}` |" in text


def test_every_kind_names_its_file_and_its_fields_once():
    assert len({k.name for k in kinds.KINDS}) == len(kinds.KINDS)
    for kind in kinds.KINDS:
        names = [f.name for f in kind.fields]
        assert len(names) == len(set(names)), kind.name
        assert not {"t_s", "kind"} & set(names), kind.name


def test_a_new_file_starts_with_its_schema_version_and_readers_take_it_out(tmp_path):
    path = tmp_path / "agent.jsonl"
    with JsonlLog(path) as log:
        log.write(kinds.WARNING, text="x")
    with JsonlLog(path) as log:  # reopened (an agent restarted): no second schema record
        log.write(kinds.WARNING, text="y")
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert [r["kind"] for r in lines] == ["schema", "warning", "warning"]
    assert lines[0]["schema_version"] == SCHEMA_VERSION and lines[0]["file"] == "agent.jsonl"
    read = read_jsonl(path)
    assert read.schema_version == SCHEMA_VERSION
    assert [r["text"] for r in read.of_kind(kinds.WARNING)] == ["x", "y"]


def test_older_files_are_read_newer_ones_refused_with_the_version_needed(tmp_path):
    old = tmp_path / "old.jsonl"  # written before versions: no schema record
    old.write_text('{"t_s": 1, "kind": "warning", "text": "x", "extra": 5}\n{"t_s": 2, "kind": "future", "a": 1}\n')
    read = read_jsonl(old)
    assert read.schema_version == 0 and 0 in READABLE_VERSIONS
    assert read.records[0]["extra"] == 5 and read.records[1]["kind"] == "future"  # unknowns are kept
    new = tmp_path / "new.jsonl"
    new.write_text(f'{{"t_s": 1, "kind": "schema", "schema_version": {SCHEMA_VERSION + 1}, "file": "new.jsonl"}}\n')
    with pytest.raises(RecordsVersionError, match=f"line 1: records of schema version {SCHEMA_VERSION + 1}; "
                                                   "this NAC reads versions") as err:
        read_jsonl(new)
    assert err.value.exit_code == 2 and str(new) in str(err.value)


def test_a_writer_that_strays_from_the_definition_fails_under_the_suite(tmp_path, monkeypatch):
    monkeypatch.setenv(STRICT_ENV, "1")
    with JsonlLog(tmp_path / "x.jsonl") as log:
        with pytest.raises(ValueError, match="record kind warning: not defined: colour"):
            log.write(kinds.WARNING, text="x", colour="red")
        with pytest.raises(ValueError, match="record kind peer_lost: missing host, silent_s"):
            log.write(kinds.PEER_LOST, peer="w1", role="worker")
    monkeypatch.delenv(STRICT_ENV)
    with JsonlLog(tmp_path / "y.jsonl") as log:  # in flight: written anyway, said once in the program's log
        log.write(kinds.WARNING, text="x", colour="red")
    assert read_jsonl(tmp_path / "y.jsonl").records[0]["colour"] == "red"


def test_the_golden_run_is_what_the_records_module_writes(tmp_path, monkeypatch):
    """tests/data/golden-run is written through JsonlLog with every field its kinds require (strict)."""
    from tests.data.make_golden_run import OUT, write_golden

    monkeypatch.setenv(STRICT_ENV, "1")
    write_golden(tmp_path)
    made = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*.jsonl"))
    assert made == sorted(p.relative_to(OUT) for p in OUT.rglob("*.jsonl"))
    for path in made:
        assert (tmp_path / path).read_text() == (OUT / path).read_text(), path
