"""One way for every command to log and to fail: a one-line message and exit code 2, never a traceback."""

from __future__ import annotations

import inspect
import logging
import os
import sys
from typing import Any, Callable


from .conf import ConfigError
from .preprocess import ImageError

__all__ = ["setup_logging", "run_cli", "api_defaults", "EXPECTED_ERRORS"]

EXPECTED_ERRORS = (ConfigError, ImageError, FileNotFoundError, PermissionError, IsADirectoryError)


def api_defaults(fn: Callable[..., object]) -> dict[str, Any]:
    """Default value of each parameter of ``fn``: CLI options take their defaults from the Python API's ``main``,
    so the two can never drift apart."""
    return {k: p.default for k, p in inspect.signature(fn).parameters.items()}


def setup_logging(verbose: bool = False) -> None:
    level = logging.DEBUG if verbose or os.environ.get("CAE_LCD_DEBUG") else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def run_cli(fn: Callable[[], object], verbose: bool = False) -> int:
    """Runs a command body; expected failures print ``error: ...`` on one line and return 2.

    Set ``CAE_LCD_DEBUG=1`` to see the traceback of an expected error as well.
    """
    setup_logging(verbose)
    try:
        fn()
    except EXPECTED_ERRORS as err:
        if os.environ.get("CAE_LCD_DEBUG"):
            logging.getLogger("cae").exception("failed")
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; everything written so far is kept (run again to resume)", file=sys.stderr)
        return 130
    return 0
