"""Progress bars that suit where the output goes: tqdm's bar on a terminal; in a log (stderr not a terminal, e.g.
``make demo > log 2>&1``), one logged line each time another ``LOG_STEP_PERCENT`` % is done instead of hundreds of
carriage-return redraws, its rate the average since the start (work that arrives in batches made tqdm's smoothed
rate read 400000 frames/s). ``Counted`` gives a generator its length, so that its bar has a total and an ETA.
"""

from __future__ import annotations

import logging
import sys
from typing import Any, Generic, Iterable, Iterator, TypeVar

from tqdm import tqdm

__all__ = ["progress_bar", "LogLines", "Counted", "LOG_STEP_PERCENT"]

T = TypeVar("T")

log = logging.getLogger("cae_lcd.progress")

LOG_STEP_PERCENT = 10  #: in a log, a line each time this many more percent are done (and one at the end)
_FORMAT = "{desc}: {percentage:3.0f}% {n_fmt}/{total_fmt} [{elapsed}<{remaining}, {rate_fmt}{postfix}]"


class _Nowhere:
    """A file that drops what tqdm writes around its display (the carriage returns and newlines)."""

    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        pass


class LogLines(tqdm):
    """A tqdm whose display is a logged line each ``LOG_STEP_PERCENT`` % (and at the end), never a redraw."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._logged = 0  # the last percentage step logged (0: none yet; the first line after LOG_STEP_PERCENT %)
        super().__init__(*args, **{**kwargs, "file": _Nowhere(), "smoothing": 0})

    def display(self, msg: str | None = None, pos: int | None = None) -> bool:  # noqa: ARG002 - tqdm's signature
        total = self.total
        if not total:
            return True
        step = int(100 * self.n / total) // LOG_STEP_PERCENT * LOG_STEP_PERCENT
        if (step > self._logged and self.n > self.initial) or (self.n >= total and self._logged < 100):
            self._logged = step
            log.info("%s", self.format_meter(**{**self.format_dict, "bar_format": _FORMAT}))
        return True


class Counted(Generic[T]):
    """An iterable of a known length (``len``), e.g. a generator of ``total`` items, for a bar with a total."""

    def __init__(self, iterable: Iterable[T], total: int) -> None:
        self.iterable, self.total = iterable, total

    def __iter__(self) -> Iterator[T]:
        return iter(self.iterable)

    def __len__(self) -> int:
        return self.total


def progress_bar(iterable: Iterable[Any] | None = None, **kwargs: Any) -> tqdm:
    """``tqdm(iterable, **kwargs)`` on a terminal; ``LogLines`` when stderr is not one (tqdm's own arguments)."""
    if kwargs.get("disable") or sys.stderr.isatty():
        return tqdm(iterable, **kwargs)
    return LogLines(iterable, mininterval=0, **{k: v for k, v in kwargs.items() if k != "mininterval"})
