"""Loop edges for a pose-graph back end: for each accepted loop, the relative pose that the verification found.

The verification (``verify.verifier``) matches the query's local features against the match's, then RANSAC on the
essential matrix gives ``R, t`` with ``x_match = R x_query + t`` for a point ``x`` in each camera's frame, i.e. the
pose of the query camera in the match camera's frame. Here it is computed again from the keyframes' features
(``LoopDetector.keyframe_features``: stored, cached, or extracted again where the run extracted them lazily) with the
run's own matcher and geometry settings (the same features as stored, keypoints kept to 1/8 pixel, and the same
deterministic RANSAC: the inliers of ``loops.csv`` within a few; a resumed run gets its edges too). ``t`` is a unit direction: from two images
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
from typing import Any, Callable, Iterable

import numpy as np

from verify.features import Features
from verify.verifier import create_verifier

__all__ = ["LoopEdge", "loop_edges", "edge_errors", "rotation_to_quaternion", "ROTATION_SIGMA_1",
           "TRANSLATION_SIGMA_1"]

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
        """``(6, 6)`` diagonal information matrix in g2o's order (translation x y z, then rotation): the module's
        rule."""
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


def loop_edges(features: Callable[[int], Features], loops: Iterable[tuple[int, int]], K: np.ndarray | None,
               conf: dict[str, Any]) -> list[LoopEdge]:
    """The relative pose of each loop, from the keyframes' local features.

    Args:
        features: a keyframe's local features by frame id (``LoopDetector.keyframe_features``).
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
        check = verifier.verify(features(int(q)), [features(int(m))], K)[0]
        geo = check.geometry
        if geo.R is not None and geo.t is not None:
            out.append(LoopEdge(int(q), int(m), int(geo.inliers), np.asarray(geo.R, np.float64),
                                np.asarray(geo.t, np.float64).reshape(3)))
    return out


def edge_errors(edges: list[LoopEdge], poses: np.ndarray) -> np.ndarray:
    """Each edge against ground-truth poses: ``(E, 2)`` rotation error and translation-direction error, degrees.

    Args:
        edges: loop edges.
        poses: ``(N, 3|4, 4)`` camera-to-world poses by frame id; the true relative pose of an edge is
            ``poses[match]^-1 poses[query]``. The translation is compared by direction only (the edge's is unit);
            NaN where the true translation is under 1 mm.
    """
    out = np.full((len(edges), 2), np.nan)
    for i, e in enumerate(edges):
        Rm, tm = poses[e.match][:3, :3], poses[e.match][:3, 3]
        R_true = Rm.T @ poses[e.query][:3, :3]
        t_true = Rm.T @ (poses[e.query][:3, 3] - tm)
        out[i, 0] = np.degrees(np.arccos(np.clip((np.trace(R_true.T @ e.R) - 1) / 2, -1.0, 1.0)))
        norm = np.linalg.norm(t_true)
        if norm > 1e-3:
            out[i, 1] = np.degrees(np.arccos(np.clip(t_true @ e.t / norm / np.linalg.norm(e.t), -1.0, 1.0)))
    return out
