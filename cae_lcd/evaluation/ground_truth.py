"""Ground-truth loop pairs: read from a pairs file, or derived from poses with a radius and a minimum gap.

Two file kinds are accepted as ground truth (``load_ground_truth`` tells them apart by their content):

- a pairs file: ``i j`` per line (0-based frame indices, ``i`` later than ``j``; ``#`` comments allowed), e.g.
  ``sequences/90/loops.txt``;
- a KITTI poses file: 12 numbers per line (3x4 camera-to-world, row-major, row ``n`` = frame ``n``), from which
  the pairs are derived with ``loops_from_poses``.

Poses are in the data set's own world (KITTI: y down; TUM, EuRoC: z up). The distance is measured on the ground
plane, across the gravity axis (``up_axis``): given (``world``: ``"y-down"``, ``"z-up"``), or found from the
trajectory (``"auto"``: the normal of a planar trajectory, else the axis the cameras' image-down direction points
along), with a warning when it cannot be told or the derived ground truth looks degenerate (the trajectory spreads
more along the axis taken as gravity than across the ground plane).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cae_lcd.core.conf import ConfigError, check_choice
from retrieval.run_folder import MAX_FRAME_ID
from retrieval.sequences import read_kitti_poses

__all__ = ["GroundTruth", "loops_from_poses", "load_ground_truth", "pair_matrix", "read_loop_pairs",
           "sniff_ground_truth", "in_run_ids", "up_axis", "check_world", "WORLDS"]

log = logging.getLogger(__name__)

_CHUNK = 1024  # rows of the distance matrix computed at once (bounds memory on long sequences)
WORLDS = {"auto": None, "y-down": 1, "z-up": 2}  #: ``world`` conventions -> the gravity axis (None: found)
_PLANAR = 0.5  #: a trajectory is planar when its thinnest spread is under this share of the next one ...
_ALIGNED = 0.9  #: ... and its normal (or the cameras' mean image-down direction) this close to one axis


def check_world(world: str) -> str:
    """``world`` when it is one of ``WORLDS`` (else ``ConfigError``)."""
    return check_choice(world, WORLDS, "--world")


def up_axis(poses: np.ndarray, world: str = "auto", what: str = "poses") -> int:
    """The gravity axis (0 x, 1 y, 2 z) of camera-to-world ``poses`` ``(N, 3, 4)``: given by ``world``
    (``WORLDS``), or found: the normal of a planar trajectory (a car, a ground robot), else the world axis the
    cameras' image-down axis points along on average (upright cameras: handheld, a drone's forward camera), else y
    (KITTI's) with a warning.

    Raises:
        ConfigError: an unknown ``world``.
    """
    check_world(world)
    poses = np.asarray(poses, np.float64).reshape(-1, 3, 4)
    if WORLDS[world] is not None or not len(poses):
        return WORLDS[world] if WORLDS[world] is not None else 1
    xyz = poses[:, :, 3] - poses[:, :, 3].mean(0)
    if len(xyz) >= 3:
        _, sv, vt = np.linalg.svd(xyz, full_matrices=False)
        normal = np.abs(vt[-1])
        if sv[-1] < _PLANAR * sv[-2] and normal.max() >= _ALIGNED:
            return int(normal.argmax())
    down = poses[:, :, 1].mean(0)
    if np.abs(down).max() >= _ALIGNED:
        return int(np.abs(down).argmax())
    log.warning("%s: cannot tell the gravity axis from the trajectory; taking y (KITTI's y-down); pass --world "
                "z-up or y-down", what)
    return 1


def _warn_if_degenerate(poses: np.ndarray, up: int, pairs: np.ndarray, what: str) -> None:
    """A warning when the ground truth derived on the plane across ``up`` looks wrong: the trajectory spreads more
    along ``up`` than across the ground plane (a wrong gravity axis), or every frame has a loop."""
    xyz = np.asarray(poses, np.float64).reshape(-1, 3, 4)[:, :, 3]
    if len(xyz) < 3:
        return
    spread = xyz.std(0)
    plane = [a for a in range(3) if a != up]
    if spread[up] > 1.0 and spread[up] > min(spread[plane]):
        log.warning("%s: the trajectory spreads %.1f m along the axis taken as gravity (%s) but %.1f m across the "
                    "ground plane: the loop ground truth is likely wrong; pass --world z-up or y-down", what,
                    spread[up], "xyz"[up], min(spread[plane]))
    elif len(pairs) and len(np.unique(pairs[:, 0])) > 0.9 * len(xyz):
        log.warning("%s: %d of %d frames have a loop in the derived ground truth: check --radius and --world",
                    what, len(np.unique(pairs[:, 0])), len(xyz))


def loops_from_poses(poses: np.ndarray, radius: float = 5.0, min_gap: int = 50,
                     timestamps: np.ndarray | None = None, min_gap_s: float | None = None, up: int = 1) -> np.ndarray:
    """Every pair of frames closer than ``radius`` metres on the ground plane and far enough apart in time.

    Args:
        poses: ``(N, 3, 4)`` camera-to-world poses.
        up: the gravity axis (1: y, KITTI's, the ground plane x-z; 2: z, TUM's and EuRoC's, the plane x-y).
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
    xz = poses[:, [a for a in range(3) if a != up], 3]
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
        up: the gravity axis the pairs were derived across (``up_axis``), for poses.
    """

    pairs: np.ndarray
    kind: str
    path: Path
    poses: np.ndarray | None = None
    up: int | None = None

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
                      timestamps: np.ndarray | None = None, min_gap_s: float | None = None,
                      world: str = "auto") -> GroundTruth:
    """Reads ground-truth pairs from a pairs file, or derives them from a KITTI poses file.

    Args:
        path: pairs file or KITTI poses file (detected from the content, see ``sniff_ground_truth``).
        radius: metres, for poses (pairs strictly closer on the x-z plane are loops).
        min_gap: minimum frame gap, for poses.
        timestamps: ``(N,)`` seconds per pose row, for ``min_gap_s``.
        min_gap_s: minimum time gap in seconds; replaces ``min_gap`` when ``timestamps`` are given.
        world: the poses' world convention (``WORLDS``: ``"auto"`` finds the gravity axis, ``up_axis``).

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
        up = up_axis(poses, world, str(path))
        pairs = loops_from_poses(poses, radius, min_gap, timestamps, min_gap_s, up)
        if len(pairs) == 0:
            log.warning("%s gives no loop pair at radius %g m: every detection will count as false and recall is "
                        "undefined", path, radius)
        _warn_if_degenerate(poses, up, pairs, str(path))
        return GroundTruth(pairs, "poses", path, poses, up)
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
    return GroundTruth(kept, truth.kind, truth.path, None if truth.poses is None else truth.poses[::stride], truth.up)


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
