"""``cae-lcd``: one entry point, one subcommand per pipeline stage (each module adds its own parser)."""

from __future__ import annotations

import argparse
import importlib
from typing import Sequence

from cae.cli import run_cli

__all__ = ["main", "SUBCOMMANDS"]

#: modules that contribute a subcommand through ``add_parser(subparsers)``
SUBCOMMANDS = ("retrieval.detect", "evaluation.evaluate", "evaluation.bench")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="cae-lcd", description="Appearance-based loop-closure detection (CAE + SIFT).")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in SUBCOMMANDS:
        importlib.import_module(module).add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return run_cli(lambda: args.func(args), verbose=args.verbose)


if __name__ == "__main__":
    raise SystemExit(main())
