"""Pictures of loops people look at: query and match side by side, one pair a cell (OpenCV, no matplotlib).

- ``loops_montage.png``: the accepted loops; with ground truth, a wrong one is framed red, a correct one green.
- ``missed_montage.png``: the queries that have a true loop and got no correct one, beside their true match (the
  middle one of the true matches of that query), framed orange.

At most ``MAX_PAIRS`` pairs are drawn (wrong loops first, then evenly spread over the rest), so a long run gives a
picture of the same size; each cell is labelled ``query -> match``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import read_image, to_uint8

__all__ = ["MAX_PAIRS", "TILE_HEIGHT", "pick_pairs", "missed_pairs", "write_montage"]

log = logging.getLogger(__name__)

MAX_PAIRS = 24  #: pairs drawn in one montage at most
TILE_HEIGHT = 120  #: pixel height of one image in a cell
COLUMNS = 2  #: cells side by side
BORDER = 6  #: frame width, pixels
COLOURS = {True: (60, 170, 60), False: (40, 40, 220), None: (200, 200, 200), "missed": (0, 150, 255)}  #: BGR frames


def pick_pairs(pairs: np.ndarray, correct: np.ndarray | None, limit: int = MAX_PAIRS) -> np.ndarray:
    """Indices of the pairs to draw, ``(<= limit,)``: every wrong one first (up to ``limit``), then the others
    spread evenly over the run."""
    order = np.arange(len(pairs))
    wrong = order[~correct] if correct is not None else order[:0]
    rest = np.setdiff1d(order, wrong)
    room = max(limit - len(wrong), 0)
    if len(rest) > room:
        rest = rest[np.unique(np.linspace(0, len(rest) - 1, room).round().astype(int))] if room else rest[:0]
    return np.concatenate([wrong[:limit], rest]).astype(np.int64)


def missed_pairs(detections: np.ndarray, correct: np.ndarray, truth_pairs: np.ndarray) -> np.ndarray:
    """``(M, 2)`` ``(query, true match)`` for each query with a true loop and no correct detection (the middle true
    match of that query), in query order."""
    found = set(detections[correct, 0].tolist()) if len(detections) else set()
    out = []
    for q in np.unique(truth_pairs[:, 0]) if len(truth_pairs) else []:
        if int(q) not in found:
            matches = np.sort(truth_pairs[truth_pairs[:, 0] == q, 1])
            out.append((int(q), int(matches[len(matches) // 2])))
    return np.array(out, np.int64).reshape(-1, 2)


def _tile(path: Path) -> np.ndarray:
    """A frame as a BGR uint8 image ``TILE_HEIGHT`` high (grey on a read error)."""
    try:
        image = to_uint8(read_image(path))
    except ImageError as err:
        log.warning("montage: %s", err)
        return np.full((TILE_HEIGHT, TILE_HEIGHT, 3), 128, np.uint8)
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    width = max(int(round(image.shape[1] * TILE_HEIGHT / image.shape[0])), 1)
    return cv2.resize(image[..., :3], (min(width, 4 * TILE_HEIGHT), TILE_HEIGHT), interpolation=cv2.INTER_AREA)


def _cell(frames: Sequence[Path], pair: np.ndarray, colour: tuple[int, int, int], label: str) -> np.ndarray:
    """Query | match, framed in ``colour``, the label written on top."""
    q, m = _tile(frames[int(pair[0])]), _tile(frames[int(pair[1])])
    body = np.concatenate([q, np.full((TILE_HEIGHT, 4, 3), 255, np.uint8), m], axis=1)
    cell = cv2.copyMakeBorder(body, BORDER + 18, BORDER, BORDER, BORDER, cv2.BORDER_CONSTANT, value=colour)
    cv2.putText(cell, label, (BORDER, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return cell


def write_montage(path: str | Path, frames: Sequence[Path], pairs: np.ndarray, correct: np.ndarray | None = None,
                  missed: bool = False, title: str = "") -> Path:
    """Draws ``pairs`` (``(P, 2)`` frame ids ``query, match``) as a grid of framed cells and writes a PNG.

    Args:
        path: PNG to write.
        frames: the sequence's frame files, indexed by frame id.
        pairs: the pairs; those picked by ``pick_pairs`` are drawn (all when there are few).
        correct: ``(P,)`` bool, whether each pair is a true loop (frames green / red); None: unknown (grey).
        missed: the pairs are missed loops (orange frames).
        title: written above the grid with the counts.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    keep = pick_pairs(pairs, None if missed else correct)
    cells = []
    for i in keep:
        ok = None if correct is None or missed else bool(correct[i])
        tag = "missed" if missed else {True: "ok", False: "WRONG", None: ""}[ok]
        cells.append(_cell(frames, pairs[i], COLOURS["missed" if missed else ok],
                           f"{pairs[i, 0]} -> {pairs[i, 1]} {tag}".strip()))
    width = max((c.shape[1] for c in cells), default=400)
    cells = [cv2.copyMakeBorder(c, 2, 2, 2, 2 + width - c.shape[1], cv2.BORDER_CONSTANT, value=(255, 255, 255))
             for c in cells]
    cells += [np.full_like(cells[0], 255)] * (-len(cells) % COLUMNS) if cells else []
    rows = [np.concatenate(cells[r:r + COLUMNS], axis=1) for r in range(0, len(cells), COLUMNS)]
    grid = np.concatenate(rows, axis=0) if rows else np.full((40, width, 3), 255, np.uint8)
    head = np.full((30, grid.shape[1], 3), 255, np.uint8)
    text = f"{title}: {len(pairs)} pairs" + (f", {len(keep)} shown" if len(keep) < len(pairs) else "")
    cv2.putText(head, text, (6, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), np.concatenate([head, grid], axis=0))
    return Path(path)
