"""The documentation tells the truth about what it points at: every relative link of README.md, docs/*.md and
deploy/README.md names a file that exists (and a heading that exists, when it names one), and every command the
documents show runs its `--help` cleanly, knowing every long option the documents give it.

Commands are read from fenced code blocks: every line of a `sh`/`bash`/`console` block, and lines that start with
`$ ` in other blocks (the rest of those is program output). A command is `nac-sitl`, `nac-onboard` or `nac-ground`,
possibly after `$ ` or `.venv/bin/`; its subcommand words are found by walking the tool's own argparse tree.
"""

from __future__ import annotations

import argparse
import functools
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = sorted([ROOT / "README.md", *(ROOT / "docs").glob("*.md"), ROOT / "deploy" / "README.md"])
BIN = Path(sys.executable).parent
PROGRAMS = ("nac-sitl", "nac-onboard", "nac-ground")
# files and `--help` processes only, no clock, no network: make test runs it beside the exclusive tests
pytestmark = pytest.mark.niced

FENCE = re.compile(r"^(`{3,}|~{3,})\s*([\w-]*)")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
CODE_SPAN = re.compile(r"`+[^`]*`+")
HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$")
SHELL_BLOCKS = {"sh", "bash", "console", "shell", "shell-session"}


def _rel(path: Path) -> str:
    return str(path.relative_to(ROOT))


def prose_and_code(path: Path) -> tuple[list[tuple[int, str]], list[tuple[int, str, str]]]:
    """(prose lines, code lines with their block's language), each with its line number."""
    prose, code, fence, language = [], [], None, ""
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        match = FENCE.match(line.lstrip())
        if match and (fence is None or match.group(1)[0] == fence[0] and len(match.group(1)) >= len(fence)):
            fence, language = (match.group(1), match.group(2).lower()) if fence is None else (None, "")
            continue
        (prose.append((number, line)) if fence is None else code.append((number, line, language)))
    return prose, code


# ---- links -----------------------------------------------------------------------------------------------------
def links(path: Path) -> list[tuple[int, str]]:
    """Every markdown link and image target outside code, with its line number (a link's text may wrap)."""
    prose, _ = prose_and_code(path)
    found = []
    for number, line in prose:  # a link whose text wraps is joined with the next line
        text = CODE_SPAN.sub("", line)
        found += [(number, m.group(1)) for m in LINK.finditer(text)]
    by_line = dict(prose)
    for number, line in prose:
        if "[" in line and number + 1 in by_line:
            joined = CODE_SPAN.sub("", line) + " " + CODE_SPAN.sub("", by_line[number + 1])
            found += [(number, m.group(1)) for m in LINK.finditer(joined)
                      if m.start() < len(line) < m.end() - 1]
    return sorted(set(found))


def is_external(target: str) -> bool:
    return bool(re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I))  # http:, https:, mailto:...


def slug(heading: str) -> str:
    """GitHub's anchor for a heading: link and code syntax dropped, lower case, punctuation gone, spaces to '-'."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading).lower()
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


@functools.cache
def anchors(path: Path) -> frozenset[str]:
    prose, _ = prose_and_code(path)
    seen: dict[str, int] = {}
    result = set()
    for _, line in prose:
        match = HEADING.match(line)
        if match:
            base = slug(match.group(1))
            result.add(base if base not in seen else f"{base}-{seen[base]}")
            seen[base] = seen.get(base, 0) + 1
    return frozenset(result)


def test_the_documents_are_found():
    names = {_rel(p) for p in DOCS}
    assert {"README.md", "deploy/README.md", "docs/sitl.md", "docs/experiments.md"} <= names


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_relative_links_name_existing_files(doc):
    missing = []
    for number, target in links(doc):
        if is_external(target) or target.startswith("#"):
            continue
        file_part = target.split("#", 1)[0].split("?", 1)[0]
        if not (doc.parent / file_part).exists():
            missing.append(f"{_rel(doc)}:{number}: ({target}) -> {file_part} does not exist")
    assert not missing, "\n".join(missing)


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_anchors_name_existing_headings(doc):
    wrong = []
    for number, target in links(doc):
        if is_external(target) or "#" not in target:
            continue
        file_part, anchor = target.split("#", 1)
        file = (doc.parent / file_part).resolve() if file_part else doc
        if file.suffix == ".md" and file.exists() and anchor not in anchors(file):
            wrong.append(f"{_rel(doc)}:{number}: ({target}): no heading #{anchor} in {_rel(file)}")
    assert not wrong, "\n".join(wrong)


# ---- commands --------------------------------------------------------------------------------------------------
@functools.cache
def parser_of(program: str) -> argparse.ArgumentParser:
    if program == "nac-sitl":
        from sitl.cli import build_parser
    elif program == "nac-onboard":
        from nac_onboard.cli import build_parser
    else:
        from ground.cli import build_parser
    return build_parser()


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _takes_value(parser: argparse.ArgumentParser, option: str) -> bool:
    action = parser._option_string_actions.get(option.split("=", 1)[0])
    return action is not None and "=" not in option and action.nargs != 0


def documented_command(line: str) -> tuple[tuple[str, ...], tuple[str, ...]] | None:
    """('nac-ground', 'mission', 'upload'), ('--connect',) from a command line; None if it is not one of ours."""
    words = re.sub(r"(^|\s)#.*$", "", line).split()  # a shell comment ends the command
    if words[:1] == ["$"]:
        words = words[1:]
    if not words:
        return None
    program = words[0].removeprefix(".venv/bin/")
    if program not in PROGRAMS:
        return None
    stop = next((i for i, w in enumerate(words) if w in ("--", "|", "&", "&&", ";", ">", "2>&1", "\\")), len(words))
    words = words[1:stop]
    path, parser, i = [program], parser_of(program), 0
    while i < len(words):
        word, choices = words[i], _subcommands(parser)
        if word.startswith("-"):
            i += 2 if _takes_value(parser, word) else 1
        elif word in choices:
            path.append(word)
            parser = choices[word]
            i += 1
        else:
            i += 1
    options = tuple(sorted({w.split("=", 1)[0] for w in words if w.startswith("--") and len(w) > 2}))
    return tuple(path), options


def documented_commands() -> dict[tuple[str, ...], dict[str, set[str]]]:
    """Each command path with the long options the documents give it, and where (file:line) for the messages."""
    found: dict[tuple[str, ...], dict[str, set[str]]] = {(program,): {} for program in PROGRAMS}
    for doc in DOCS:
        _, code = prose_and_code(doc)
        for number, line, language in code:
            text = line.strip()
            if language not in SHELL_BLOCKS and not text.startswith("$ "):
                continue
            command = documented_command(text)
            if command is None:
                continue
            path, options = command
            uses = found.setdefault(path, {})
            for option in options:
                uses.setdefault(option, set()).add(f"{_rel(doc)}:{number}")
    return found


COMMANDS = documented_commands()


@functools.cache
def help_text(path: tuple[str, ...]) -> str:
    program = BIN / path[0]
    assert program.exists(), f"{program} is not installed (pip install -e . into this venv)"
    done = subprocess.run([str(program), *path[1:], "--help"], capture_output=True, text=True, timeout=60,
                          stdin=subprocess.DEVNULL)
    output = done.stdout + done.stderr
    assert done.returncode == 0 and "Traceback" not in output, (
        f"{' '.join(path)} --help exited {done.returncode}:\n{output[-3000:]}")
    assert "usage:" in done.stdout, f"{' '.join(path)} --help printed no usage:\n{output[-3000:]}"
    return done.stdout


def test_documented_commands_are_found():
    assert len(COMMANDS) > len(PROGRAMS)  # more than the three top levels: the documents show their commands
    assert ("nac-sitl", "experiment") in COMMANDS and ("nac-ground", "mission", "upload") in COMMANDS


@pytest.mark.parametrize("path", sorted(COMMANDS), ids=" ".join)
def test_documented_command_has_help(path):
    help_text(path)  # exits 0, prints usage, no traceback
    unknown = []
    for option, where in sorted(COMMANDS[path].items()):
        # an option may belong to the command or to one of the commands above it (nac-ground --connect ...)
        if not any(re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", help_text(path[:n]))
                   for n in range(len(path), 0, -1)):
            unknown.append(f"{option} (in {', '.join(sorted(where))})")
    assert not unknown, f"{' '.join(path)} has no option " + "; ".join(unknown)


def test_the_documented_parameter_count_is_the_simulators():
    """README and docs/sitl.md said 48 parameters when there were 52 (issue 33)."""
    from sitl.vehicle.params import PARAM_DEFS

    count = len(PARAM_DEFS)
    assert f"its {count} parameters" in (ROOT / "README.md").read_text()
    assert f"Parameters ({count}, `PARAM_DEFS`" in (ROOT / "docs" / "sitl.md").read_text()
