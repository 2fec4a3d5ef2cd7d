"""Write command_table.py, every MAV_CMD MAVLink's XML definitions define, from checkouts of the definitions.

    python -m nac_onboard.mavlink.make_command_table MAVLINK_CHECKOUT [MAVLINK_CHECKOUT...]

Each checkout (mavlink/mavlink, ArduPilot/mavlink) is read from its `message_definitions/v1.0/all.xml`, which
includes every dialect, following the includes. Missions may hold commands newer than the installed pymavlink's
generated dialect (ArduPilot flies them before pymavlink is released again): with this table, NAC knows them by
name and still refuses a number no dialect defines. Run it again when the definitions gain commands.
"""

from __future__ import annotations

import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

TABLE = Path(__file__).with_name("command_table.py")
DEFINITIONS = "message_definitions/v1.0"


def _dialect(checkout: Path, name: str, seen: set[str], found: dict[int, tuple[str, bool]]) -> None:
    if name in seen:
        return
    seen.add(name)
    root = ET.parse(checkout / DEFINITIONS / name).getroot()
    for include in root.findall("include"):
        _dialect(checkout, (include.text or "").strip(), seen, found)
    if name == "all.xml":  # its own entries are placeholders (MAV_CMD_DUMMY_ALL), not commands
        return
    for enum in root.iter("enum"):
        if enum.get("name") == "MAV_CMD":
            for entry in enum.findall("entry"):
                found.setdefault(int(entry.get("value")), (entry.get("name").removeprefix("MAV_CMD_"),
                                                           entry.get("hasLocation") == "true"))


def _revision(checkout: Path) -> str:
    done = subprocess.run(["git", "-C", str(checkout), "log", "-1", "--format=%H %cs"], capture_output=True,
                          text=True, timeout=30)
    return done.stdout.strip() or "(not a git checkout)"


def main(argv: list[str] | None = None) -> int:
    checkouts = [Path(p) for p in (argv if argv is not None else sys.argv[1:])]
    if not checkouts:
        print(__doc__, file=sys.stderr)
        return 2
    found: dict[int, tuple[str, bool]] = {}
    sources = []
    for checkout in checkouts:
        if not (checkout / DEFINITIONS / "all.xml").is_file():
            print(f"make_command_table: {checkout}: no {DEFINITIONS}/all.xml", file=sys.stderr)
            return 2
        _dialect(checkout, "all.xml", set(), found)
        sources.append(f"{checkout.name}: {_revision(checkout)}")
    rows = "\n".join(f"    {number}: ({name!r}, {located}),"
                     for number, (name, located) in sorted(found.items()))
    TABLE.write_text('"""Every MAV_CMD of MAVLink\'s XML definitions (all.xml and what it includes): number -> '
                     '(name without MAV_CMD_,\nparams 5-7 are a location). Written by make_command_table.py from:\n'
                     + "".join(f"- {s}\n" for s in sources) + '"""\n\n'
                     f"COMMANDS: dict[int, tuple[str, bool]] = {{\n{rows}\n}}\n")
    print(f"{TABLE}: {len(found)} commands")
    return 0


if __name__ == "__main__":
    sys.exit(main())
