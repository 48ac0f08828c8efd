"""Revisits found in an unlabeled folder: the pairs of frames far apart in time that are one place.

A folder of frames read in name order is a sequence. Where the camera came back to a place (a second traversal, a
route driven in summer and again in winter, a station the train waited at), single codes are weak evidence, but a
*stretch* of consecutive frames that matches another stretch on one offset is strong: the sequence matching of
SeqSLAM. The training (``cae.train``, ``revisit_z``) uses the revisits found this way as positives of the place
term, beside the two views of a frame and its temporal neighbour, and never as negatives: without them a folder
that revisits its places teaches the code to push a place's two visits apart, exactly what a loop detector must
not learn. No label is read.

The rule, per folder: codes whitened by a PCA fitted on the folder's own codes (``cae.whitening``); the similarity
of frames ``i`` and ``j`` fused over the ``2 * span + 1`` frame pairs ``(i + d, j + d)`` of their line; for each
frame its best partner at least ``far`` frames away; kept when that fused similarity is a clear outlier of the
frame's own row (robust z-score, median and MAD of every partner at least ``far`` away, at least ``z_min``) and
the partner's best line comes back to within 2 frames of the frame (mutual). On ../shared: Nordland (a summer and a
winter traversal in one folder) with the default weights' codes gives 861 of 1000 frames a partner, every one the
same place (755 the other season's frame within 2, 106 the other end of a station stop); KITTI 00 and 07 (no
revisit) give none.

Shapes: codes ``(N, D)``; folder ids and positions ``(N,)`` int. Numpy in and out.
"""

from __future__ import annotations

import numpy as np

from .whitening import MIN_FIT_CODES, Whitening

__all__ = ["fused_similarity", "mine_revisits", "MUTUAL_SLACK"]

MUTUAL_SLACK = 2  #: the partner's best line may come back this many frames beside the frame


def fused_similarity(codes: np.ndarray, span: int) -> np.ndarray:
    """``(N, N)`` float32: cosine of whitened codes, averaged over each pair's line ``(i + d, j + d)``,
    ``|d| <= span`` (the pairs of the line that exist).

    Args:
        codes: ``(N, D)`` codes of one sequence, in order.
        span: frames either side fused (0: single frames).
    """
    n = len(codes)
    if n == 0:
        return np.zeros((0, 0), np.float32)
    x = Whitening.fit(codes).transform(codes) if n >= MIN_FIT_CODES else \
        codes / np.maximum(np.linalg.norm(codes, axis=1, keepdims=True), 1e-12)
    sims = (x @ x.T).astype(np.float32)
    total, count = np.zeros_like(sims), np.zeros_like(sims)
    for d in range(-span, span + 1):
        lo, hi = max(0, -d), min(n, n - d)
        if hi <= lo:
            continue
        total[lo:hi, lo:hi] += sims[lo + d:hi + d, lo + d:hi + d]
        count[lo:hi, lo:hi] += 1
    return total / np.maximum(count, 1)


def _one_folder(codes: np.ndarray, far: int, span: int, z_min: float) -> np.ndarray:
    """``(M, 2)`` positions ``(i, j)`` of one folder's revisits (each frame at most once as ``i``)."""
    n = len(codes)
    fused = fused_similarity(codes, span)
    gap = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    fused[gap < far] = -np.inf
    best = fused.argmax(1)
    out = []
    for i in range(n):
        row = fused[i][np.isfinite(fused[i])]
        if len(row) < 2 * MIN_FIT_CODES:
            continue
        med = float(np.median(row))
        mad = 1.4826 * float(np.median(np.abs(row - med))) + 1e-9
        j = int(best[i])
        if (fused[i, j] - med) / mad >= z_min and abs(int(best[j]) - i) <= MUTUAL_SLACK:
            out.append((i, j))
    return np.asarray(out, np.int64).reshape(-1, 2)


def mine_revisits(codes: np.ndarray, folder: np.ndarray, position: np.ndarray, far: int, span: int = 5,
                  z_min: float = 6.0) -> np.ndarray:
    """The revisits of every folder (see the module's rule).

    Args:
        codes: ``(N, D)`` codes of every frame of the set.
        folder: ``(N,)`` folder id of each frame.
        position: ``(N,)`` its rank in its folder (name order = time order).
        far: fewest frames between a frame and its revisit (nearer frames are its temporal neighbours).
        span: frames either side fused along each pair's line.
        z_min: the fewest robust standard deviations the best line must stand above the frame's other lines.

    Returns:
        ``(M, 2)`` int64 indices into the set, ``(i, j)`` one place; ``(0, 2)`` for none.
    """
    codes, folder, position = np.asarray(codes, np.float32), np.asarray(folder), np.asarray(position)
    pairs = [np.zeros((0, 2), np.int64)]
    for f in np.unique(folder):
        members = np.flatnonzero(folder == f)
        members = members[np.argsort(position[members], kind="stable")]
        found = _one_folder(codes[members], far, span, z_min)
        pairs.append(members[found])
    return np.concatenate(pairs)
