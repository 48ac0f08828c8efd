"""Loop edges for a pose-graph back end: for each accepted loop, the relative pose that the verification found.

The verification (``verify.verifier``) matches the query's local features against the match's, then RANSAC on the
essential matrix gives ``R, t`` with ``x_match = R x_query + t`` for a point ``x`` in each camera's frame, i.e. the
pose of the query camera in the match camera's frame. Here it is computed again from the features stored in the
keyframe database with the run's own matcher and geometry settings (same features, same deterministic RANSAC: the
same inliers as ``loops.csv``, so a resumed run gets its edges too). ``t`` is a unit direction: from two images
without depth the length of the baseline cannot be known, so **the translation is up to scale**.

Information matrix (the rule, in g2o's order ``x y z`` then the three rotation components): each of the ``n``
inliers is taken as one independent measurement, so variances shrink as ``1 / n``::

    sigma_rot(n)   = ROTATION_SIGMA_1 / sqrt(n)      radians
    sigma_trans(n) = TRANSLATION_SIGMA_1 / sqrt(n)   in units of the unit translation (scale unknown)
    information    = diag(1/sigma_trans^2 x 3, 1/sigma_rot^2 x 3)

``ROTATION_SIGMA_1 = 0.1`` rad makes 100 inliers a 0.57-degree standard deviation, above the rotation errors measured
on KITTI 90 (``python -m bench.loop_edges``, BENCHMARKS.md), so the edges are not over-confident; the translation
stays weak on purpose (a back end should fit its scale or down-weight it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from verify.verifier import create_verifier

__all__ = ["LoopEdge", "loop_edges", "rotation_to_quaternion", "ROTATION_SIGMA_1", "TRANSLATION_SIGMA_1"]

ROTATION_SIGMA_1 = 0.1  #: rotation standard deviation (radians) an edge would have from one inlier
TRANSLATION_SIGMA_1 = 1.0  #: translation-direction standard deviation from one inlier (the translation is unit)


@dataclass(frozen=True)
class LoopEdge:
    """One loop as a relative pose: the query camera in the match camera's frame (``x_match = R x_query + t``)."""

    query: int  #: the later frame (the g2o edge's second vertex)
    match: int  #: the earlier frame it closes on (the g2o edge's first vertex)
    inliers: int  #: geometric inliers of the verification
    R: np.ndarray  #: (3, 3) rotation, query camera -> match camera
    t: np.ndarray  #: (3,) unit translation direction (scale unknown)

    def information(self) -> np.ndarray:
        """``(6, 6)`` diagonal information matrix, g2o order (translation x y z, then rotation), by the module's rule."""
        n = max(self.inliers, 1)
        return np.diag([n / TRANSLATION_SIGMA_1**2] * 3 + [n / ROTATION_SIGMA_1**2] * 3)

    def quaternion(self) -> np.ndarray:
        """``(4,)`` ``qx, qy, qz, qw`` of ``R`` (g2o's order), ``qw >= 0``."""
        return rotation_to_quaternion(self.R)


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """A ``(3, 3)`` rotation matrix -> ``(4,)`` unit quaternion ``qx, qy, qz, qw`` with ``qw >= 0``.

    The quaternion is the eigenvector of the largest eigenvalue of Bar-Itzhack's symmetric 4x4 matrix, which is
    exact for a rotation and the nearest quaternion for a slightly non-orthonormal matrix.
    """
    R = np.asarray(R, np.float64).reshape(3, 3)
    (a, b, c), (d, e, f), (g, h, i) = R
    Kmat = np.array([[a - e - i, d + b, g + c, h - f],
                     [d + b, e - a - i, h + f, c - g],
                     [g + c, h + f, i - a - e, d - b],
                     [h - f, c - g, d - b, a + e + i]]) / 3.0
    q = np.linalg.eigh(Kmat)[1][:, -1]
    return q if q[3] >= 0 else -q


def loop_edges(db: Any, loops: Iterable[tuple[int, int]], K: np.ndarray | None,
               conf: dict[str, Any]) -> list[LoopEdge]:
    """The relative pose of each loop, from the features in the keyframe database.

    Args:
        db: the run's ``KeyframeDatabase`` (``features(frame_id)``).
        loops: ``(query, match)`` frame id pairs (``(L, 2)``), as ``RunFolder.write_tables`` returns them.
        K: ``(3, 3)`` intrinsics; None: no edges (without intrinsics the geometry is a fundamental matrix, no pose).
        conf: the run's resolved conf (its ``matcher`` and ``geometry`` sections are used).

    Returns:
        One ``LoopEdge`` per loop whose essential matrix gave a pose, in the order of ``loops``; ``[]`` without ``K``.
    """
    if K is None:
        return []
    verifier = create_verifier(conf.get("matcher"), conf.get("geometry"))
    out = []
    for q, m in loops:
        check = verifier.verify(db.features(int(q)), [db.features(int(m))], K)[0]
        geo = check.geometry
        if geo.R is not None and geo.t is not None:
            out.append(LoopEdge(int(q), int(m), int(geo.inliers), np.asarray(geo.R, np.float64),
                                np.asarray(geo.t, np.float64).reshape(3)))
    return out
