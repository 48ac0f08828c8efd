"""One way for every command to log and to fail: a one-line message and an exit code, never a traceback.

Exit codes: 0 success; 2 an expected error (bad argument, config value, input file, damaged or unwritable output:
``error: ...``); 1 an internal error, i.e. a bug (``internal error: ...``, with the traceback under
``CAE_LCD_DEBUG=1``); 130 interrupted.
"""

from __future__ import annotations

import argparse
import inspect
import logging
import os
import sys
from typing import Any, Callable

from .errors import ConfigError, LCDError

__all__ = ["setup_logging", "run_cli", "api_defaults", "add_missing_extra", "add_unavailable", "EXPECTED_ERRORS"]

#: errors that are the user's input or environment, not a bug: reported as ``error: ...`` with exit code 2
EXPECTED_ERRORS = (LCDError, OSError, MemoryError)


def api_defaults(fn: Callable[..., object]) -> dict[str, Any]:
    """Default value of each parameter of ``fn``: CLI options take their defaults from the Python API's ``main``,
    so the two can never drift apart."""
    return {k: p.default for k, p in inspect.signature(fn).parameters.items()}


def add_missing_extra(sub: Any, command: str, extra: str, err: ImportError) -> None:
    """Adds ``command`` as a subcommand that only says which optional extra it needs (its package is missing)."""
    add_unavailable(sub, command, f"cae-lcd {command} needs the '{extra}' extra ({err.name or err} is not "
                    f"installed): pip install 'cae-loop-closure[{extra}]'", f"needs the '{extra}' extra")


def add_unavailable(sub: Any, command: str, why: str, short: str) -> None:
    """Adds ``command`` as a subcommand that cannot run here and only says ``why`` (``short`` in the help list)."""
    p = sub.add_parser(command, help=f"({short})", description=why, prefix_chars="\x01")
    p.add_argument("args", nargs="*", help=argparse.SUPPRESS)  # whatever was passed: the command cannot run anyway

    def refuse(args: Any) -> None:
        raise ConfigError(why)

    p.set_defaults(func=refuse)


def setup_logging(verbose: bool = False) -> None:
    level = logging.DEBUG if verbose or os.environ.get("CAE_LCD_DEBUG") else logging.INFO
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _one_line(err: BaseException) -> str:
    if isinstance(err, OSError) and not isinstance(err, LCDError) and err.strerror:
        text = f"{err.strerror}: {err.filename}" if err.filename else err.strerror
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())


def run_cli(fn: Callable[[], object], verbose: bool = False) -> int:
    """Runs a command body; failures print one line on stderr and return an exit code (see the module doc).

    Set ``CAE_LCD_DEBUG=1`` to see the traceback as well.
    """
    setup_logging(verbose)
    debug = bool(os.environ.get("CAE_LCD_DEBUG"))
    try:
        fn()
    except EXPECTED_ERRORS as err:
        if debug:
            logging.getLogger("cae_lcd").exception("failed")
        print(f"error: {_one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; everything written so far is kept (run again to resume)", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - a bug: still one line, the traceback on request
        if debug:
            logging.getLogger("cae_lcd").exception("internal error")
        print(f"internal error (a bug, please report it): {type(err).__name__}: {_one_line(err)[:300]} "
              "(set CAE_LCD_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1
    return 0
