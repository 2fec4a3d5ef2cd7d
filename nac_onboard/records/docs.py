"""docs/records.md, made from the definitions in kinds.py (`python -m nac_onboard.records [--check]`)."""

from __future__ import annotations

from nac_onboard.records import kinds
from nac_onboard.records.schema import READABLE_VERSIONS, SCHEMA_VERSION

HEADER = """# A run's records

Made by `python -m nac_onboard.records` from `nac_onboard/records/kinds.py`, the one place that names a run
directory's files and record kinds; do not edit by hand. Every JSON Lines file holds one record per line,
`{{"t_s": unix seconds, "kind": NAME, ...fields}}`, and starts with a `schema` record: this code writes schema
version {version} and reads versions {readable} (0: a file written before versions, with the same fields).
A reader keeps kinds and fields it does not know; a file of a newer version is refused with the version it needs
(exit 2). Optional fields may be absent or null (JSON has no NaN: an unknown number is null).

"""


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def markdown() -> str:
    out = [HEADER.format(version=SCHEMA_VERSION, readable=", ".join(map(str, READABLE_VERSIONS)))]
    out += ["## Files\n", "| path in the run directory | one per | JSON Lines | written by | what it holds |",
            "| --- | --- | --- | --- | --- |"]
    out += [f"| `{f.path}` | {f.per} | {'yes' if f.jsonl else 'no'} | {_cell(f.writer)} | {_cell(f.doc)} |"
            for f in kinds.FILES]
    out.append(f"\nBeside them, a vehicle's folder may hold autopilot logs (`.tlog`, `.bin`, `.ulg`) and iperf3's "
               f"own output as `{kinds.IPERF3_GLOB}`, which the analysis reads too.\n")
    for file in (kinds.ANY_FILE, *(f for f in kinds.FILES if f.jsonl)):
        members = [k for k in kinds.KINDS if k.file is file]
        out.append(f"## `{file.path}`\n")
        for kind in members:
            out.append(f"### `{kind.name}`\n\n{kind.doc}. Written by {kind.file.writer}.\n")
            out += ["| field | type | unit | required | meaning |", "| --- | --- | --- | --- | --- |"]
            out += [f"| `{f.name}` | {f.type} | {f.unit} | {'no' if f.optional else 'yes'} | {_cell(f.doc)} |"
                    for f in kind.fields]
            if kind.open:
                out.append(f"| ... | | | no | {_cell(kind.open)} |")
            out.append("")
    return "\n".join(out).rstrip() + "\n"
