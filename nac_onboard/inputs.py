"""The checks every input edge shares: ids, finite numbers in a range, and files read whole.

Scenarios, agent configs, channel files, parameter files, flight logs and command-line arguments all go through
these, so a bad value is refused the same way everywhere, before anything starts: BadInput (exit 2) with a
sentence naming the file, the field and what was expected.

- An id (a vehicle's, a scenario's) becomes a directory name, an MPI host name and a label in a page: 1-32 of
  `[A-Za-z0-9._-]`, and neither `.` nor `..`. A run's name (a directory of the log root: a scenario's name and
  its start time) is the same alphabet, up to 128 characters.
- A number is finite (no NaN, no infinity), not a bool, and within its range.
- A file is a regular file (a FIFO would block the reader forever, /dev/zero never ends, a directory is no file),
  checked with os.stat before it is opened, opened without blocking, and read up to its kind's size limit (a
  bounded read: a file that grows past the limit while read is refused too, and a sparse 2 GB file is never
  loaded).

Standard library only (and nac_onboard.errors), so every part can use it; `missions`, which imports nothing of
NAC's, keeps its own copy of the file check (missions/plan.py).
"""

from __future__ import annotations

import math
import os
import re
import stat
from pathlib import Path

from nac_onboard.errors import BadInput

MiB = 1024 * 1024
MAX_CONFIG_BYTES = 4 * MiB  # an agent config, a scenario, a channel TOML, a parameter file, a key, a positions script
MAX_LOG_BYTES = 256 * MiB  # one JSON Lines log or iperf3 JSON (a day of probes is a few tens of MB)
MAX_AUTOPILOT_LOG_BYTES = 1024 * MiB  # a .tlog, DataFlash .bin or .ulg (a 15-minute flight is tens of MB)

ID_RULE = "1-32 letters, digits, '.', '_' or '-' (not '.' or '..')"
_ID = re.compile(r"[A-Za-z0-9._-]{1,32}")
# a run's name: a directory of the log root, made of a scenario's name (an id) and its start time
NAME_RULE = "1-128 letters, digits, '.', '_' or '-' (not '.' or '..')"
_NAME = re.compile(r"[A-Za-z0-9._-]{1,128}")


def is_id(value) -> bool:
    return isinstance(value, str) and _ID.fullmatch(value) is not None and value not in (".", "..")


def check_id(value, where: str, error: type[BadInput] = BadInput) -> str:
    """value if it is an id (see ID_RULE); else `error` naming `where`."""
    if not is_id(value):
        raise error(f"{where}: expected an id of {ID_RULE}, got {_shown(value)}")
    return value


def is_name(value) -> bool:
    return isinstance(value, str) and _NAME.fullmatch(value) is not None and value not in (".", "..")


def check_name(value, where: str, error: type[BadInput] = BadInput) -> str:
    """value if it can be a directory's name in a log root (see NAME_RULE: an id, or longer, as a run's name
    of a scenario's name and a time); else `error` naming `where`."""
    if not is_name(value):
        raise error(f"{where}: expected a name of {NAME_RULE}, got {_shown(value)}")
    return value


def check_number(value, where: str, low: float | None = None, high: float | None = None, *, integer: bool = False,
                 low_open: bool = False, error: type[BadInput] = BadInput, unit: str = ""):
    """value as an int (integer=True) or float, finite and within [low, high] (`low_open`: (low, high]); else
    `error` naming `where` and the range."""
    expected = f"{'an integer' if integer else 'a finite number'}{_range(low, high, low_open, unit)}"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or (integer and not isinstance(value, int)):
        raise error(f"{where}: expected {expected}, got {_shown(value)}")
    if not integer and not math.isfinite(value):
        raise error(f"{where}: expected {expected}, got {value!r}")
    if (low is not None and (value <= low if low_open else value < low)) or (high is not None and value > high):
        raise error(f"{where}: expected {expected}, got {value!r}")
    return int(value) if integer else float(value)


def parse_number(text: str, where: str, low: float | None = None, high: float | None = None, *,
                 integer: bool = False, low_open: bool = False, error: type[BadInput] = BadInput,
                 unit: str = ""):
    """A number from text (a command-line argument), checked as check_number does."""
    try:
        value = int(text, 10) if integer else float(text)
    except (TypeError, ValueError):
        raise error(f"{where}: expected {'an integer' if integer else 'a finite number'}"
                    f"{_range(low, high, low_open, unit)}, got {_shown(text)}") from None
    return check_number(value, where, low, high, integer=integer, low_open=low_open, error=error, unit=unit)


def number_arg(low: float | None = None, high: float | None = None, *, integer: bool = False,
               low_open: bool = False, unit: str = ""):
    """An argparse `type=` checking a finite number in range: argparse names the option and exits 2."""
    import argparse

    def parse(text: str):
        try:
            return parse_number(text, "value", low, high, integer=integer, low_open=low_open, unit=unit)
        except BadInput as err:
            raise argparse.ArgumentTypeError(str(err).removeprefix("value: ")) from None

    parse.__name__ = "integer" if integer else "number"
    return parse


def id_arg(text: str) -> str:
    """An argparse `type=` for an id."""
    import argparse

    if not is_id(text):
        raise argparse.ArgumentTypeError(f"expected an id of {ID_RULE}, got {_shown(text)}")
    return text


def name_arg(text: str) -> str:
    """An argparse `type=` for a run's name (see check_name)."""
    import argparse

    if not is_name(text):
        raise argparse.ArgumentTypeError(f"expected a name of {NAME_RULE}, got {_shown(text)}")
    return text


def check_regular_file(path: str | Path, what: str, limit_bytes: int,
                       error: type[BadInput] = BadInput) -> os.stat_result:
    """The file's stat if it is a regular file of at most limit_bytes; else `error` naming it and why. For files
    another library opens by name (pandas, pymavlink): a FIFO or device never reaches it."""
    try:
        st = os.stat(path)
    except OSError as err:
        raise error(f"cannot read {what} {path}: {err.strerror or err}") from None
    _check_stat(st, path, what, limit_bytes, error)
    return st


def read_bounded(path: str | Path, what: str, limit_bytes: int, error: type[BadInput] = BadInput) -> bytes:
    """The whole of a regular file of at most limit_bytes, read without blocking; `error` names the file and
    what was wrong (missing, not a regular file, too large, unreadable)."""
    check_regular_file(path, what, limit_bytes, error)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | getattr(os, "O_CLOEXEC", 0))
    except OSError as err:
        raise error(f"cannot read {what} {path}: {err.strerror or err}") from None
    try:
        _check_stat(os.fstat(fd), path, what, limit_bytes, error)  # the file opened is the one checked
        chunks, total = [], 0
        while total <= limit_bytes:
            chunk = os.read(fd, min(limit_bytes + 1 - total, 4 * MiB))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except BlockingIOError:
        raise error(f"cannot read {what} {path}: it blocks (not a regular file)") from None
    except OSError as err:
        raise error(f"cannot read {what} {path}: {err.strerror or err}") from None
    finally:
        os.close(fd)
    if total > limit_bytes:
        raise error(f"{what} {path}: grew past {_size(limit_bytes)} while read; a {what} may have at most that")
    return b"".join(chunks)


def read_bounded_text(path: str | Path, what: str, limit_bytes: int = MAX_CONFIG_BYTES,
                      error: type[BadInput] = BadInput) -> str:
    """read_bounded as UTF-8 text (a BOM tolerated); undecodable bytes are `error` naming the offset."""
    data = read_bounded(path, what, limit_bytes, error)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise error(f"{what} {path}: not UTF-8 text (byte {err.start})") from None


def inside(directory: str | Path, name: str | Path, where: str, error: type[BadInput] = BadInput) -> Path:
    """directory/name, refused unless it stays inside directory (no `..`, no absolute name, no symlink out)."""
    base = Path(directory).resolve()
    target = (base / name).resolve()
    if target == base or base not in target.parents:
        raise error(f"{where}: {_shown(str(name))} leaves its directory {directory}")
    return base / name


def _check_stat(st: os.stat_result, path, what: str, limit_bytes: int, error: type[BadInput]) -> None:
    mode = st.st_mode
    if not stat.S_ISREG(mode):
        kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode) else
                "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "a socket" if stat.S_ISSOCK(mode)
                else "not a file")
        raise error(f"{what} {path}: is {kind}; expected a regular file")
    if st.st_size > limit_bytes:
        raise error(f"{what} {path}: {_size(st.st_size)}; a {what} may have at most {_size(limit_bytes)}")


def _size(n: int) -> str:
    return f"{n / MiB:.1f} MiB" if n >= MiB else f"{n} bytes"


def _range(low, high, low_open: bool, unit: str) -> str:
    unit = f" {unit}" if unit else ""
    if low is not None and high is not None:
        return f" within {'(' if low_open else '['}{_num(low)}, {_num(high)}]{unit}"
    if low is not None:
        return f" {'>' if low_open else '>='} {_num(low)}{unit}"
    if high is not None:
        return f" <= {_num(high)}{unit}"
    return ""


def _num(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e13 else f"{x:g}"


def _shown(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
