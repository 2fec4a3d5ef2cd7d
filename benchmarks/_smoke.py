"""The `--smoke` flag every benchmark has: the same code path with tiny sizes, so the test suite runs them all."""

from __future__ import annotations

import argparse


def parse_args(parser: argparse.ArgumentParser, smoke_defaults: dict) -> argparse.Namespace:
    """parser's arguments; with --smoke, smoke_defaults replace the defaults (explicit flags still win)."""
    parser.add_argument("--smoke", action="store_true", help=f"tiny run to check the benchmark works: {smoke_defaults}")
    if parser.parse_known_args()[0].smoke:
        parser.set_defaults(**smoke_defaults)
    return parser.parse_args()
