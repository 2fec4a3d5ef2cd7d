"""TOML at the edges, one way: read a file, check a table into a frozen dataclass (types and units from the
dataclass's own fields), and write a file back. Agent configs, channel presets and scenarios all go through here,
so a wrong key or type is reported the same way everywhere: file, table, key, what was expected."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

from nac_onboard.errors import BadInput
from nac_onboard.inputs import MAX_CONFIG_BYTES, check_number, read_bounded_text

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

_MISSING = object()


def read_toml(path: str | Path, what: str, error: type[BadInput] = BadInput,
              limit_bytes: int = MAX_CONFIG_BYTES) -> dict:
    """The file's tables; `error` names the file and the parser's line and column. Only a regular file of at most
    limit_bytes is read (nac_onboard.inputs.read_bounded: a FIFO or /dev/zero is refused, never waited on)."""
    path = Path(path)
    text = read_bounded_text(path, what, limit_bytes, error)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise error(f"{path}: not valid TOML: {err}") from None
    except RecursionError:
        raise error(f"{path}: not valid TOML: nested too deeply") from None


def ranged(default=dataclasses.MISSING, low: float | None = None, high: float | None = None, *,
           low_open: bool = False, unit: str = ""):
    """A dataclass field whose TOML value must lie within [low, high] ((low, high] with low_open): to_dataclass
    refuses anything else naming the key and the range."""
    return dataclasses.field(default=default, metadata={"range": (low, high, low_open, unit)})


def check_value(value, type_name: str, where: str, error: type[BadInput] = BadInput):
    """value converted to the field type named (bool, int, float, str, tuple of str; `X | None` as X, or None
    from the string "none": TOML has no null, and an override must be able to unset a preset's value)."""
    if type_name.endswith(" | None") and (value is None or value == "none"):
        return None
    type_name = type_name.removesuffix(" | None")
    if type_name == "bool":
        if isinstance(value, bool):
            return value
        raise error(f"{where}: expected true or false, got {value!r}")
    if type_name == "int":
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise error(f"{where}: expected an integer, got {value!r}")
    if type_name == "float":
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise error(f"{where}: expected a finite number, got {value!r}")
    if type_name == "str":
        if isinstance(value, str):
            return value
        raise error(f"{where}: expected a string, got {value!r}")
    if type_name.startswith("tuple"):
        if isinstance(value, list) and all(isinstance(v, str) for v in value):
            return tuple(value)
        raise error(f"{where}: expected a list of strings, got {value!r}")
    raise TypeError(f"{where}: field type {type_name} cannot come from TOML")


def get_value(table: dict, key: str, type_name: str, where: str, error: type[BadInput] = BadInput,
              default=_MISSING):
    """table[key] checked as type_name, or default; a missing key without default is an error naming it."""
    if key not in table:
        if default is _MISSING:
            raise error(f"{where}: missing key {key!r}")
        return default
    return check_value(table[key], type_name, f"{where}: {key}", error)


def to_dataclass(cls, values: dict, where: str, error: type[BadInput] = BadInput, table: str | None = None,
                 **fixed):
    """An instance of the frozen dataclass cls from a TOML table (named `table` in messages): unknown keys, missing
    required keys and wrong types are errors naming `where` and the key. `fixed` fields come from the caller."""
    prefix = f"{table}." if table else ""
    if not isinstance(values, dict):
        raise error(f"{where}: [{table}] must be a table")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name not in fixed and f.init}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise error(f"{where}: unknown key {prefix}{unknown[0]} (known: {', '.join(fields)})")
    checked = {}
    for key, value in values.items():
        checked[key] = value = check_value(value, str(fields[key].type), f"{where}: {prefix}{key}", error)
        limits = fields[key].metadata.get("range")
        if limits is not None and value is not None:
            low, high, low_open, unit = limits
            check_number(value, f"{where}: {prefix}{key}", low, high, integer=isinstance(value, int),
                         low_open=low_open, error=error, unit=unit)
    missing = [f.name for f in fields.values() if f.name not in checked
               and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    if missing:
        raise error(f"{where}: {f'[{table}] ' if table else ''}needs {', '.join(missing)}")
    return cls(**checked, **fixed)


def dumps_toml(values: dict) -> str:
    """TOML text of scalars, lists and one level of tables (what configs and presets hold); None is left out."""
    lines = [f"{key} = {_value(value)}" for key, value in values.items()
             if value is not None and not isinstance(value, dict)]
    for name, table in values.items():
        if isinstance(table, dict):
            lines += ["", f"[{name}]"] if lines else [f"[{name}]"]
            lines += [f"{key} = {_value(value)}" for key, value in table.items() if value is not None]
    return "\n".join(lines) + "\n"


def write_toml(path: str | Path, values: dict) -> None:
    Path(path).write_text(dumps_toml(values))


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'
