"""`nac-ground`: the operator's command line (mission, vehicle and log commands arrive in later issues)."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="nac-ground", description=__doc__)
    parser.add_argument("command", nargs="?", choices=["mission", "status", "monitor", "logs"])
    args, _rest = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    print(f"nac-ground {args.command}: not implemented yet (planned: missions, vehicle commands, log analysis).",
          file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
