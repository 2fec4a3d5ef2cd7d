"""What a record kind is: its name, the file it lives in, who writes it, and its fields with units.

A field's `type` is what JSON holds (number, integer, string, boolean, list, object; "any" where it varies);
`optional` fields may be absent or null. Writers are checked against the definition when NAC_RECORDS_STRICT is set
(the test suite sets it, so a field written but not defined, or a required one left out, fails a test); in flight a
mismatch is logged once per kind and the record is written anyway: a log line is never worth a lost record.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)

#: Every JSON Lines file of a run starts with a `schema` record carrying this number. Raise it when a field changes
#: meaning or a required field is removed or renamed; adding a kind or an optional field keeps it.
SCHEMA_VERSION = 1
#: Versions this code reads. 0 is a file without a schema record: written before versions (2026-11-25 and earlier),
#: with the same fields as version 1.
READABLE_VERSIONS = (0, 1)
STRICT_ENV = "NAC_RECORDS_STRICT"


@dataclass(frozen=True)
class Field:
    name: str
    type: str
    unit: str
    doc: str
    optional: bool = False


def req(name: str, type_: str, unit: str, doc: str) -> Field:
    return Field(name, type_, unit, doc)


def opt(name: str, type_: str, unit: str, doc: str) -> Field:
    return Field(name, type_, unit, doc, optional=True)


@dataclass(frozen=True)
class RunFile:
    """A file of a run directory. `path` is relative to the run directory, with VEHICLE for a vehicle's id and N
    for an MPI rank; `per` says how many there are."""

    name: str
    path: str
    per: str  # "run", "vehicle", "rank"
    writer: str
    doc: str
    jsonl: bool = True

    def at(self, run_dir: str | Path, vehicle: str | None = None, rank: int | None = None) -> Path:
        """This file's path in a run directory (a vehicle's or a rank's where the path has one)."""
        return Path(run_dir) / self._fill(self.path, vehicle, rank)

    def file_name(self, vehicle: str | None = None, rank: int | None = None) -> str:
        return self._fill(self.name, vehicle, rank)

    def _fill(self, text: str, vehicle: str | None, rank: int | None) -> str:
        if "VEHICLE" in text:
            if vehicle is None:
                raise ValueError(f"{self.path}: which vehicle?")
            text = text.replace("VEHICLE", vehicle)
        if "-N." in text:
            if rank is None:
                raise ValueError(f"{self.path}: which rank?")
            text = text.replace("-N.", f"-{rank}.")
        return text


@dataclass(frozen=True)
class Kind:
    """One record kind: `{"t_s": unix seconds, "kind": name, **fields}`, one per line of `file`."""

    name: str
    file: RunFile
    doc: str
    fields: tuple[Field, ...] = ()
    open: str = ""  # non-empty: fields beyond these are expected, and this says whose they are
    _names: frozenset = field(default=frozenset(), repr=False, compare=False)
    _required: frozenset = field(default=frozenset(), repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "_names", frozenset(f.name for f in self.fields) | {"t_s", "kind"})
        object.__setattr__(self, "_required", frozenset(f.name for f in self.fields if not f.optional))

    def __str__(self) -> str:
        return self.name

    def mismatch(self, fields: dict) -> str | None:
        """What is wrong with these fields for this kind, or None."""
        missing = self._required.difference(fields)
        unknown = () if self.open else set(fields).difference(self._names)
        if not missing and not unknown:
            return None
        parts = []
        if missing:
            parts.append(f"missing {', '.join(sorted(missing))}")
        if unknown:
            parts.append(f"not defined: {', '.join(sorted(unknown))} (add them to nac_onboard/records/kinds.py)")
        return f"record kind {self.name}: {'; '.join(parts)}"


_warned: set[str] = set()


def check(kind: Kind, fields: dict) -> None:
    problem = kind.mismatch(fields)
    if problem is None:
        return
    if os.environ.get(STRICT_ENV):
        raise ValueError(problem)
    if kind.name not in _warned:
        _warned.add(kind.name)
        log.warning("%s (written anyway)", problem)
