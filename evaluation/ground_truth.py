"""Ground-truth loop pairs: read from a pairs file, or derived from poses with a radius and a minimum gap."""

from __future__ import annotations

import numpy as np

__all__ = ["loops_from_poses"]


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
    """
    poses = np.asarray(poses, np.float64).reshape(-1, 3, 4)
    n = len(poses)
    if n == 0:
        return np.zeros((0, 2), np.int64)
    xz = poses[:, [0, 2], 3]
    d = np.linalg.norm(xz[:, None, :] - xz[None, :, :], axis=2)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    if min_gap_s is not None and timestamps is not None:
        t = np.asarray(timestamps, np.float64)
        far = (t[:, None] - t[None, :]) >= min_gap_s
    else:
        far = (i - j) >= min_gap
    sel = (d < radius) & far & (i > j)
    return np.stack([i[sel], j[sel]], axis=1).astype(np.int64)
