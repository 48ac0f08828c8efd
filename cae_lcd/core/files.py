"""Writing files so that a crash or a full disk never leaves half a file where a good one was."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import IO, Iterator

from .errors import ConfigError, DatabaseError

__all__ = ["atomic_write", "write_text_atomic", "prepare_out_dir"]


@contextlib.contextmanager
def atomic_write(path: str | Path, mode: str = "w", **kwargs: object) -> Iterator[IO]:
    """Opens a temporary file beside ``path``; on success it replaces ``path`` (rename), on error it is removed and
    ``path`` keeps its old content.

    Raises:
        DatabaseError: the file cannot be written (disk full, read-only, ...); ``path`` is unchanged.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        with open(tmp, mode, **kwargs) as f:  # type: ignore[call-overload]
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as err:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise DatabaseError(f"cannot write {path}: {err.strerror or err}; the previous file is kept") from None
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """``path.write_text(text)``, atomically (see ``atomic_write``)."""
    with atomic_write(path, "w", encoding="utf-8") as f:
        f.write(text)


def prepare_out_dir(out: str | Path, what: str = "--out") -> Path:
    """Creates the output folder (and parents) and checks that files can be written there.

    Raises:
        ConfigError: ``out`` is a file, lies under a file, is not writable, or cannot be created; says which.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{what} {out} exists and is not a folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise ConfigError(f"{what} {out}: a parent of it is a file, not a folder") from None
    except NotADirectoryError:
        raise ConfigError(f"{what} {out}: a parent of it is a file, not a folder") from None
    except OSError as err:
        raise ConfigError(f"{what} {out} cannot be created: {err.strerror or err}") from None
    probe = out / f".write-test-{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise ConfigError(f"{what} {out} is not writable: {err.strerror or err}") from None
    return out
