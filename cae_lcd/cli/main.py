"""``cae-lcd COMMAND``: one entry point, one module per command in this package (each adds its own parser).

Every command reports a failure as one ``error: ...`` line with exit code 2, never a traceback (``cae_lcd.core.cli``).
"""

from __future__ import annotations

import argparse
from importlib import metadata
from typing import Sequence

from cae_lcd.core.cli import run_cli

from . import bench, calibrate, detect, evaluate, fleet_demo, serve, train

__all__ = ["main", "build_parser", "version", "COMMANDS", "DISTRIBUTION"]

DISTRIBUTION = "cae-loop-closure"  #: the name the package is installed under

COMMANDS = (detect, calibrate, evaluate, bench, train, serve, fleet_demo)  #: modules that contribute a subcommand through ``add_parser(subparsers)``


class _Parser(argparse.ArgumentParser):
    """argparse, with its usage errors as one ``error:`` line and exit code 2 like every other failure."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"error: {self.prog}: {message}\n")


def version() -> str:
    """The installed package's version (its one home is ``pyproject.toml``)."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "unknown (not installed: pip install -e .)"


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="cae-lcd", description="Appearance-based loop-closure detection (CAE + SIFT).")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for module in COMMANDS:
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Runs ``cae-lcd`` with ``argv`` (default: ``sys.argv[1:]``); returns the exit code."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as stop:  # --help, or a usage error already printed as one line
        return int(stop.code or 0)
    return run_cli(lambda: args.func(args), verbose=args.verbose)


if __name__ == "__main__":
    raise SystemExit(main())
