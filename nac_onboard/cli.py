"""`nac-onboard`: the companion computer's command line (agent and compute arrive in later issues)."""

from __future__ import annotations

import argparse
import sys


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="nac-onboard", description=__doc__)
    parser.add_argument("command", nargs="?", choices=["agent", "compute"])
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 0
    print(f"nac-onboard {args.command}: not implemented yet (planned: onboard agent and MPI compute).",
          file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
