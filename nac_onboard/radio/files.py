"""The radio's files, the one module of nac_onboard.radio that reads or writes any: channel models as TOML
(a preset by name, or what `nac-ground logs calibrate` and the experiment runner write) and the replay tables a
channel can name (JSON). Everything else in the package is pure and takes the loaded objects.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from nac_onboard.inputs import MAX_LOG_BYTES, read_bounded_text
from nac_onboard.radio.channel import PRESETS, ChannelError, ChannelModel
from nac_onboard.radio.replay import EXPECTED_JSON, ReplayError, ReplayLinks
from nac_onboard.tomlfile import read_toml, to_dataclass, write_toml


def load_channel(name_or_path: str) -> ChannelModel:
    """A preset by name, or a TOML file of ChannelModel fields (what `nac-ground logs calibrate` writes)."""
    if name_or_path in PRESETS:
        return PRESETS[name_or_path]
    path = Path(name_or_path)
    if not path.exists():
        raise ChannelError(f"channel {name_or_path!r}: not a preset ({', '.join(PRESETS)}) nor a file")
    values = read_toml(path, "channel model", ChannelError)
    values.setdefault("name", path.stem)
    return to_dataclass(ChannelModel, values, str(path), ChannelError)


def save_channel(model: ChannelModel, path: str | Path) -> None:
    write_toml(path, dataclasses.asdict(model))


def load_replay(path: str | Path) -> ReplayLinks:
    try:
        data = json.loads(read_bounded_text(path, "replay table", MAX_LOG_BYTES, ReplayError))
    except ReplayError:
        raise
    except (ValueError, RecursionError) as err:
        raise ReplayError(f"{path}: not a replay table (expected {EXPECTED_JSON}): {err}") from None
    return ReplayLinks.from_json(data, str(path))


def save_replay(table: ReplayLinks, path: str | Path) -> None:
    Path(path).write_text(json.dumps(table.to_json()) + "\n")
