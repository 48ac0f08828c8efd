"""Ground-truth loop pairs: read from a pairs file, or derived from poses with a radius and a minimum gap.

Two file kinds are accepted as ground truth (``load_ground_truth`` tells them apart by their content):

- a pairs file: ``i j`` per line (0-based frame indices, ``i`` later than ``j``; ``#`` comments allowed), e.g.
  ``sequences/90/loops.txt``;
- a KITTI poses file: 12 numbers per line (3x4 camera-to-world, row-major, row ``n`` = frame ``n``), from which
  the pairs are derived with ``loops_from_poses``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from core.conf import ConfigError
from retrieval.run_folder import MAX_FRAME_ID
from retrieval.sequences import read_kitti_poses

__all__ = ["GroundTruth", "loops_from_poses", "load_ground_truth", "pair_matrix", "read_loop_pairs",
           "sniff_ground_truth", "in_run_ids"]

log = logging.getLogger(__name__)

_CHUNK = 1024  # rows of the distance matrix computed at once (bounds memory on long sequences)


def loops_from_poses(poses: np.ndarray, radius: float = 5.0, min_gap: int = 50,
                     timestamps: np.ndarray | None = None, min_gap_s: float | None = None) -> np.ndarray:
    """Every pair of frames closer than ``radius`` metres on the ground plane (x-z) and far enough apart in time.

    Args:
        poses: ``(N, 3, 4)`` camera-to-world poses (KITTI convention: x-z is the ground plane).
        radius: distance threshold, metres (pairs strictly closer count).
        min_gap: minimum index gap ``i - j`` (used when ``min_gap_s`` is None).
        timestamps: ``(N,)`` seconds, with ``min_gap_s``.
        min_gap_s: minimum time gap in seconds; replaces ``min_gap`` when given with timestamps.

    Returns:
        ``(P, 2)`` int64 pairs ``(i, j)`` with ``i > j``, sorted by ``i`` then ``j``; ``(0, 2)`` when none.

    Raises:
        ConfigError: ``timestamps`` given with ``min_gap_s`` but of another length than ``poses``.
    """
    poses = np.asarray(poses, np.float64).reshape(-1, 3, 4)
    n = len(poses)
    if n == 0:
        return np.zeros((0, 2), np.int64)
    use_time = min_gap_s is not None and timestamps is not None
    if use_time:
        t = np.asarray(timestamps, np.float64).reshape(-1)
        if len(t) != n:
            raise ConfigError(f"{len(t)} timestamps for {n} poses; the time gap needs one timestamp per pose")
    xz = poses[:, [0, 2], 3]
    out = []
    for start in range(0, n, _CHUNK):
        rows = np.arange(start, min(n, start + _CHUNK))
        d = np.linalg.norm(xz[rows, None, :] - xz[None, :, :], axis=2)
        i, j = np.meshgrid(rows, np.arange(n), indexing="ij")
        far = (t[rows, None] - t[None, :]) >= min_gap_s if use_time else (i - j) >= min_gap
        sel = (d < radius) & far & (i > j)
        out.append(np.stack([i[sel], j[sel]], axis=1))
    return np.concatenate(out).astype(np.int64).reshape(-1, 2)


@dataclass
class GroundTruth:
    """Ground truth of one sequence.

    Attributes:
        pairs: ``(P, 2)`` int64 ``(later, earlier)`` true loop pairs, sorted.
        kind: ``"pairs"`` (read from a pairs file) or ``"poses"`` (derived from a KITTI poses file).
        path: the file it came from.
        poses: ``(N, 3, 4)`` camera-to-world poses when ``kind == "poses"``, else None.
    """

    pairs: np.ndarray
    kind: str
    path: Path
    poses: np.ndarray | None = None

    @property
    def queries(self) -> np.ndarray:
        """``(Q,)`` int64 frames that have at least one true loop (the recall denominator), sorted."""
        return np.unique(self.pairs[:, 0]) if len(self.pairs) else np.zeros(0, np.int64)


def read_loop_pairs(path: str | Path) -> np.ndarray:
    """Loop pairs file (``i j`` per line, ``#`` comments) -> ``(P, 2)`` int64 rows (later, earlier), unique, sorted.

    Raises:
        ConfigError: missing or unreadable file, or a line that is not two frame indices in 0..``MAX_FRAME_ID``
            (file and line named).
    """
    path = Path(path)
    rows = []
    for n, parts in _numeric_rows(path, numbered=True):
        try:
            i, j = (int(v) for v in parts)
        except ValueError:
            raise ConfigError(f"{path}, line {n}: expected two frame indices 'i j', got {' '.join(parts)[:60]!r}") \
                from None
        if min(i, j) < 0 or max(i, j) > MAX_FRAME_ID:
            raise ConfigError(f"{path}, line {n}: frame indices must be in 0..{MAX_FRAME_ID}")
        rows.append((i, j))
    pairs = np.array(rows, dtype=np.int64).reshape(-1, 2)
    return np.unique(np.stack([pairs.max(1), pairs.min(1)], axis=1), axis=0) if len(pairs) else pairs


def _numeric_rows(path: Path, numbered: bool = False) -> list:
    if not path.is_file():
        raise ConfigError(f"ground-truth file not found: {path}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read ground-truth file {path}: {err}") from None
    rows = [(n, line.split("#")[0].split()) for n, line in enumerate(text.splitlines(), 1)]
    rows = [(n, parts) for n, parts in rows if parts]
    return rows if numbered else [parts for _, parts in rows]


def _parses(s: str, kind: type) -> bool:
    try:
        kind(s)
    except ValueError:
        return False
    return True


def sniff_ground_truth(path: str | Path) -> str:
    """Tells a pairs file (``"pairs"``: 2 integers a line) from a KITTI poses file (``"poses"``: 12 numbers a line).

    An empty file (or only comments) is a pairs file with no pair.

    Raises:
        ConfigError: missing file, or lines that are neither (the message names the first offending line).
    """
    path = Path(path)
    rows = _numeric_rows(path)
    if not rows:
        return "pairs"
    if len(rows[0]) == 12 and all(len(r) == 12 and all(_parses(v, float) for v in r) for r in rows):
        return "poses"
    if all(len(r) == 2 and all(_parses(v, int) for v in r) for r in rows):
        return "pairs"
    bad = next((n for n, r in enumerate(rows, 1) if not (len(r) == 2 and all(_parses(v, int) for v in r))
                and not (len(r) == 12 and all(_parses(v, float) for v in r))), None)
    what = ("mixes pair lines and pose lines" if bad is None
            else f"data line {bad} is {' '.join(rows[bad - 1])[:60]!r}")
    raise ConfigError(f"{path}: not a ground-truth file (need 'i j' integer pairs, or KITTI poses with 12 numbers "
                      f"a line); {what}")


def load_ground_truth(path: str | Path, radius: float = 5.0, min_gap: int = 50,
                      timestamps: np.ndarray | None = None, min_gap_s: float | None = None) -> GroundTruth:
    """Reads ground-truth pairs from a pairs file, or derives them from a KITTI poses file.

    Args:
        path: pairs file or KITTI poses file (detected from the content, see ``sniff_ground_truth``).
        radius: metres, for poses (pairs strictly closer on the x-z plane are loops).
        min_gap: minimum frame gap, for poses.
        timestamps: ``(N,)`` seconds per pose row, for ``min_gap_s``.
        min_gap_s: minimum time gap in seconds; replaces ``min_gap`` when ``timestamps`` are given.

    Returns:
        ``GroundTruth`` with pairs ``(P, 2)`` as ``(later, earlier)``, unique and sorted.

    Raises:
        ConfigError: missing or unrecognised file, or negative frame indices.
    """
    path = Path(path)
    kind = sniff_ground_truth(path)
    if kind == "poses":
        poses = read_kitti_poses(path)
        if min_gap_s is not None and timestamps is None:
            log.warning("min_gap_s=%s given without timestamps; using the frame gap %d instead", min_gap_s, min_gap)
        pairs = loops_from_poses(poses, radius, min_gap, timestamps, min_gap_s)
        if len(pairs) == 0:
            log.warning("%s gives no loop pair at radius %g m: every detection will count as false and recall is "
                        "undefined", path, radius)
        return GroundTruth(pairs, "poses", path, poses)
    pairs = read_loop_pairs(path)
    if len(pairs) == 0:
        log.warning("%s holds no loop pair: every detection will count as false and recall is undefined", path)
    return GroundTruth(pairs, "pairs", path)


def in_run_ids(truth: GroundTruth, stride: int) -> GroundTruth:
    """Ground truth numbered by the source's frames (a video's frame numbers) -> numbered as a run that took every
    ``stride``-th frame numbers them: pairs of frames it read, ids divided by ``stride``; poses every ``stride``-th.
    """
    if stride <= 1:
        return truth
    p = truth.pairs
    kept = p[(p % stride == 0).all(axis=1)] // stride
    log.info("%s: frames numbered in the source; a run of every %d-th frame keeps %d of its %d pairs", truth.path,
             stride, len(kept), len(p))
    return GroundTruth(kept, truth.kind, truth.path, None if truth.poses is None else truth.poses[::stride])


def pair_matrix(pairs: np.ndarray, n: int) -> np.ndarray:
    """Symmetric boolean ``(n, n)`` matrix, True at every pair (pairs with an index >= n are dropped).

    Args:
        pairs: ``(P, 2)`` int frame-index pairs, either order.
        n: number of frames.
    """
    m = np.zeros((max(0, n), max(0, n)), bool)
    p = np.asarray(pairs, np.int64).reshape(-1, 2)
    p = p[(p >= 0).all(1) & (p < n).all(1)]
    m[p[:, 0], p[:, 1]] = True
    m[p[:, 1], p[:, 0]] = True
    return m
