"""The project's errors. Every entry point turns them into one ``error: ...`` line (``cae_lcd.core.cli.run_cli``).

All derive from ``LCDError``; ``ConfigError`` and ``ImageError`` are also ``ValueError`` (a bad value was given),
``DatabaseError`` is also an ``OSError`` (a file on disk is damaged, locked or unwritable).
"""

from __future__ import annotations

__all__ = ["LCDError", "ConfigError", "ConflictError", "ImageError", "DatabaseError", "printable"]


def printable(text: str) -> str:
    """``text`` with a file name's undecodable bytes (which Python keeps as lone surrogates) as ``\\udcff`` escapes:
    writable as UTF-8 anywhere (a log file, a table, a test report)."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


class LCDError(Exception):
    """Base of every error this project raises on purpose; the message says what and where (``printable``: a name
    that is not UTF-8 is written with escapes)."""

    def __init__(self, *args: object) -> None:
        super().__init__(*(printable(a) if isinstance(a, str) else a for a in args))


class ConfigError(LCDError, ValueError):
    """A configuration value, an argument, or an input file named by them is invalid."""


class ConflictError(ConfigError):
    """A value that contradicts one already accepted (e.g. a retry of an acknowledged id with other content)."""


class ImageError(LCDError, ValueError):
    """An image could not be read or has a layout we cannot interpret."""


class DatabaseError(LCDError, OSError):
    """A file we wrote (keyframe database, run tables) is damaged, locked by another process or cannot be written."""
