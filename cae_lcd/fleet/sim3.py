"""Similarity transforms of 3D points, ``x -> s R x + t``: Umeyama's closed form and RANSAC with a robust refinement.

Two robots' maps differ by a similarity (monocular SLAM fixes its scale arbitrarily), so the transform between them
is estimated from 3D-3D point matches: ``umeyama`` solves the least-squares problem in closed form (Umeyama, "Least-
squares estimation of transformation parameters between two point patterns", PAMI 1991; the same solution as Horn's
absolute orientation with scale), and ``ransac_sim3`` finds it among outliers (minimal samples of 3 pairs, MSAC
scoring, adaptive stopping) and refines it by iteratively reweighted Umeyama (Huber or Cauchy weights).

Errors: ``umeyama`` raises ``ConfigError`` (a ``ValueError``) with one line for anything it cannot solve: arrays of
the wrong shape, NaN or inf, fewer than 3 points, or points that are coincident or collinear. ``ransac_sim3`` raises
``ConfigError`` only for malformed arrays (shape, NaN, inf) and returns ``None`` where the data hold no transform
(fewer points than ``min_inliers``, only degenerate samples, too few inliers).

numpy in, numpy out: points are ``(n, 3)`` float arrays.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from cae_lcd.core.conf import Bool, Choice, ConfigError, Float, Int, configure

__all__ = ["Sim3", "umeyama", "Sim3Ransac", "ransac_sim3", "check_point_pairs"]

log = logging.getLogger(__name__)

#: a fit is degenerate (collinear or coincident points) when the second singular value of the cross-covariance is
#: under this fraction of the first
_RANK_TOL = 1e-9
#: a minimal RANSAC sample is skipped when its triangle is this thin (second / first singular value)
_SAMPLE_TOL = 1e-2
_CHUNK = 2_000_000  #: hypotheses x points scored at once (memory bound of the residual array)


@dataclass(frozen=True)
class Sim3:
    """A 3D similarity ``x -> s R x + t``; ``s > 0``, ``R`` a rotation (det +1). Immutable.

    Attributes:
        s: scale.
        R: ``(3, 3)`` rotation.
        t: ``(3,)`` translation.
    """

    s: float
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        s = float(self.s)
        R = np.array(self.R, np.float64)
        t = np.array(self.t, np.float64).reshape(-1)
        if not (math.isfinite(s) and s > 0):
            raise ConfigError(f"Sim3 scale must be a finite number > 0; got {self.s!r}")
        if R.shape != (3, 3) or t.shape != (3,) or not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise ConfigError(f"Sim3 needs a finite (3, 3) R and (3,) t; got {R.shape} and {t.shape}")
        if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
            raise ConfigError("Sim3 R must be a rotation (orthonormal, det +1); got a reflection or a non-rotation")
        R.flags.writeable = False
        t.flags.writeable = False
        object.__setattr__(self, "s", s)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)

    @classmethod
    def identity(cls) -> "Sim3":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, M: np.ndarray) -> "Sim3":
        """``(4, 4)`` or ``(3, 4)`` ``[[s R, t], [0, 1]]`` -> ``Sim3`` (scale from the determinant).

        Raises:
            ConfigError: wrong shape, or the 3x3 block is not a positive multiple of a rotation.
        """
        M = np.asarray(M, np.float64)
        if M.shape not in ((3, 4), (4, 4)):
            raise ConfigError(f"a similarity matrix is (4, 4) or (3, 4); got {M.shape}")
        if not np.isfinite(M).all():
            raise ConfigError("a similarity matrix needs finite entries")
        with np.errstate(over="ignore", invalid="ignore"):  # an overflowing determinant is refused just below
            det = np.linalg.det(M[:3, :3])
        if not (det > 0 and np.isfinite(det)):
            raise ConfigError("a similarity matrix needs a 3x3 block with a positive, finite determinant")
        s = float(np.cbrt(det))
        return cls(s, M[:3, :3] / s, M[:3, 3])

    @classmethod
    def from_pose(cls, pose: np.ndarray, tol: float = 1e-3) -> "Sim3":
        """A robot's ``(3, 4)`` or ``(4, 4)`` pose -> ``Sim3``; a 3x3 block that is a rotation (times a scale) up to
        ``tol`` is projected onto the nearest one (SLAM systems and text files round).

        Raises:
            ConfigError: wrong shape, NaN/inf, a last row other than ``0 0 0 1``, or a block that is no similarity.
        """
        M = np.asarray(pose, np.float64)
        if M.shape not in ((3, 4), (4, 4)) or not np.isfinite(M).all():
            raise ConfigError(f"a pose is a finite (3, 4) or (4, 4) matrix; got shape {M.shape}")
        if M.shape == (4, 4) and np.abs(M[3] - [0, 0, 0, 1]).max() > tol:
            raise ConfigError("a (4, 4) pose must end with the row 0 0 0 1")
        U, d, Vt = np.linalg.svd(M[:3, :3])
        if np.linalg.det(U @ Vt) <= 0 or d[0] <= 0 or (d[0] - d[2]) > tol * d[0]:
            raise ConfigError("a pose's 3x3 block must be a rotation (or a rotation times a scale)")
        return cls(float(np.cbrt(np.prod(d))), U @ Vt, M[:3, 3])

    def matrix(self) -> np.ndarray:
        """``(4, 4)`` homogeneous matrix ``[[s R, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.s * self.R
        M[:3, 3] = self.t
        return M

    def apply(self, points: np.ndarray) -> np.ndarray:
        """``(n, 3)`` (or ``(3,)``) points -> the transformed points, same shape."""
        p = np.asarray(points, np.float64)
        return self.s * p @ self.R.T + self.t

    def inverse(self) -> "Sim3":
        """The similarity that undoes this one."""
        return Sim3(1.0 / self.s, self.R.T, -self.R.T @ self.t / self.s)

    def compose(self, other: "Sim3") -> "Sim3":
        """``self o other``: apply ``other`` first, then ``self``."""
        return Sim3(self.s * other.s, self.R @ other.R, self.s * self.R @ other.t + self.t)

    def to(self, other: "Sim3") -> "Sim3":
        """``self^-1 o other``: ``other`` seen from ``self``, the edge between two poses (odometry: the previous
        keyframe's pose ``.to`` the current one's)."""
        return self.inverse().compose(other)

    def errors(self, reference: "Sim3") -> tuple[float, float, float]:
        """How far this transform is from ``reference``.

        Returns:
            ``(rotation angle in degrees, |s / s_ref - 1|, ||t - t_ref||)``.
        """
        D = self.R @ reference.R.T
        sin = np.linalg.norm([D[2, 1] - D[1, 2], D[0, 2] - D[2, 0], D[1, 0] - D[0, 1]]) / 2.0
        angle = math.degrees(math.atan2(sin, (np.trace(D) - 1.0) / 2.0))  # exact near 0, unlike acos
        return angle, abs(self.s / reference.s - 1.0), float(np.linalg.norm(self.t - reference.t))


def check_point_pairs(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both point sets as float64 ``(n, 3)`` arrays.

    Raises:
        ConfigError: not ``(n, 3)`` each with the same ``n``, or a NaN/inf coordinate.
    """
    a = np.asarray(src, np.float64)
    b = np.asarray(dst, np.float64)
    if a.ndim != 2 or a.shape[1:] != (3,) or a.shape != b.shape:
        raise ConfigError(f"src and dst must be (n, 3) arrays of the same n; got {a.shape} and {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ConfigError("src and dst must be finite; got NaN or inf coordinates")
    return a, b


def _fit_batch(src: np.ndarray, dst: np.ndarray, w: np.ndarray, with_scale: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weighted Umeyama for ``k`` problems at once.

    Args:
        src: ``(k, n, 3)`` source points.
        dst: ``(k, n, 3)`` destination points.
        w: ``(k, n)`` non-negative weights, each row with a positive sum.
        with_scale: estimate ``s``; else ``s = 1``.

    Returns:
        ``s (k,)``, ``R (k, 3, 3)``, ``t (k, 3)`` and the spread ``(k,)``: second over first singular value of the
        cross-covariance (near 0: collinear or coincident points, the fit is meaningless).
    """
    wn = w / w.sum(axis=1, keepdims=True)
    with np.errstate(over="ignore", invalid="ignore"):
        mu_s = np.einsum("kn,knd->kd", wn, src)
        mu_d = np.einsum("kn,knd->kd", wn, dst)
        a = src - mu_s[:, None]
        b = dst - mu_d[:, None]
        cov = np.einsum("kn,kni,knj->kij", wn, b, a)
    # LAPACK never returns on an infinite matrix (points so far apart that their products overflow): such problems
    # are solved as the zero matrix, whose spread 0 marks them degenerate
    finite = np.isfinite(cov).all(axis=(1, 2))
    U, D, Vt = np.linalg.svd(np.where(finite[:, None, None], cov, 0.0))
    D[~finite] = 0.0
    flip = np.ones((len(D), 3))
    flip[:, 2] = np.where(np.linalg.det(U) * np.linalg.det(Vt) < 0, -1.0, 1.0)  # a reflection -> the best rotation
    R = U @ (flip[:, :, None] * Vt)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        spread = D[:, 1] / D[:, 0]
        var_s = np.einsum("kn,knd,knd->k", wn, a, a)
        s = (D * flip).sum(axis=1) / var_s if with_scale else np.ones(len(D))
    t = mu_d - s[:, None] * np.einsum("kij,kj->ki", R, mu_s)
    return s, R, t, np.nan_to_num(spread)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = True, weights: np.ndarray | None = None) -> Sim3:
    """The least-squares similarity ``T`` with ``dst ~ T.apply(src)`` (Umeyama 1991), reflections excluded.

    Args:
        src: ``(n, 3)`` points.
        dst: ``(n, 3)`` matching points, same order.
        with_scale: estimate the scale (sim(3)); False gives a rigid transform (``s = 1``).
        weights: ``(n,)`` non-negative weights (None: all 1); points of weight 0 do not count.

    Returns:
        ``Sim3`` minimising ``sum_i w_i ||dst_i - (s R src_i + t)||^2``.

    Raises:
        ConfigError: malformed arrays, bad weights, fewer than 3 weighted points, or coincident/collinear points.
    """
    a, b = check_point_pairs(src, dst)
    w = np.ones(len(a)) if weights is None else np.asarray(weights, np.float64).reshape(-1)
    if w.shape != (len(a),) or not np.isfinite(w).all() or (w < 0).any():
        raise ConfigError(f"weights must be {len(a)} finite numbers >= 0; got shape {w.shape}")
    if np.count_nonzero(w) < 3:
        raise ConfigError(f"a similarity needs at least 3 point pairs; got {np.count_nonzero(w)}")
    s, R, t, spread = _fit_batch(a[None], b[None], w[None], with_scale)
    if not spread[0] > _RANK_TOL or not (np.isfinite(s[0]) and s[0] > 0):
        raise ConfigError("the points are coincident, collinear or too far apart: no unique similarity")
    return Sim3(float(s[0]), R[0], t[0])


def _residuals(s: np.ndarray, R: np.ndarray, t: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``(k, n)`` distances ``||s R src + t - dst||`` of ``k`` hypotheses (``s (k,)``, ``R (k,3,3)``, ``t (k,3)``)."""
    with np.errstate(over="ignore", invalid="ignore"):  # points far apart: inf, never an inlier
        pred = s[:, None, None] * np.einsum("kij,nj->kni", R, src) + t[:, None]
        return np.linalg.norm(pred - dst[None], axis=2)


def _robust_weights(r: np.ndarray, scale: float, loss: str) -> np.ndarray:
    """IRLS weights of residuals ``r (n,)``: Huber ``min(1, scale / r)`` or Cauchy ``1 / (1 + (r / scale)^2)``."""
    if loss == "huber":
        return np.minimum(1.0, scale / np.maximum(r, 1e-300))
    return 1.0 / (1.0 + (r / scale) ** 2)


class Sim3Ransac:
    """RANSAC for the similarity between two matched point sets, then a robust refinement.

    The inlier threshold is a distance in the ``dst`` frame: with ``threshold_mode: relative`` it is ``threshold``
    times the scene scale (the median distance of the ``dst`` points to their per-axis median), so the same conf
    serves maps of any unit and scale (monocular SLAM); with ``absolute`` it is ``threshold`` in ``dst`` units
    (metres when ``dst`` is metric). Hypotheses come from random samples of 3 pairs (thin triangles skipped) and are
    scored by MSAC (truncated squared residuals); sampling stops once ``confidence`` is reached. The best hypothesis
    is refined by iteratively reweighted Umeyama on its inliers (weights by ``loss`` with scale half the threshold).
    """

    default_conf: dict[str, Any] = {
        "threshold": 0.05,  # inlier distance: a fraction of the scene scale (relative) or dst units (absolute)
        "threshold_mode": "relative",  # "relative" (scale-free, see the class doc) or "absolute" (dst units)
        "iterations": 2000,  # most minimal samples drawn (3 point pairs each)
        "confidence": 0.999,  # stop sampling once an all-inlier sample was drawn with this probability
        "min_inliers": 6,  # fewer inliers (or fewer points): no transform, None
        "with_scale": True,  # estimate the scale (sim(3)); false: rigid transform (SE(3)), s = 1
        "refine_iterations": 10,  # iteratively reweighted Umeyama steps after RANSAC (0: none)
        "loss": "huber",  # robust weights of the refinement: "huber" or "cauchy"
        "seed": 0,  # random generator seed: the same input and conf give the same result
    }
    conf_rules: dict[str, Any] = {
        "threshold": Float(0, lo_open=True), "threshold_mode": Choice("relative", "absolute"),
        "iterations": Int(1, 10_000_000), "confidence": Float(0, 1, lo_open=True, hi_open=True),
        "min_inliers": Int(3), "with_scale": Bool(), "refine_iterations": Int(0, 1000),
        "loss": Choice("huber", "cauchy"), "seed": Int(0)}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "sim3")

    def threshold_for(self, dst: np.ndarray) -> float:
        """The inlier distance for points ``dst (n, 3)`` in ``dst`` units (0 when they have no spread)."""
        if self.conf["threshold_mode"] == "absolute":
            return float(self.conf["threshold"])
        with np.errstate(over="ignore", invalid="ignore"):
            scene = float(np.median(np.linalg.norm(dst - np.median(dst, axis=0), axis=1))) if len(dst) else 0.0
        return self.conf["threshold"] * scene

    def __call__(self, src: np.ndarray, dst: np.ndarray) -> tuple[Sim3, np.ndarray] | None:
        """Estimates ``T`` with ``dst ~ T.apply(src)`` among outliers.

        Args:
            src: ``(n, 3)`` points.
            dst: ``(n, 3)`` matching points, same order.

        Returns:
            ``(Sim3, inliers (n,) bool)``, or None where the data hold no transform (see the module doc).

        Raises:
            ConfigError: malformed arrays (shape, NaN, inf).
        """
        a, b = check_point_pairs(src, dst)
        thr = self.threshold_for(b)
        if len(a) < self.conf["min_inliers"] or not thr > 0:
            return None
        best = self._sample(a, b, thr)
        if best is None:
            return None
        model = self._refine(a, b, best, thr)
        mask = _residuals(np.array([model.s]), model.R[None], model.t[None], a, b)[0] < thr
        if mask.sum() < self.conf["min_inliers"]:
            return None
        log.debug("sim3 RANSAC: %d of %d inliers, s=%.4f", mask.sum(), len(a), model.s)
        return model, mask

    def _sample(self, a: np.ndarray, b: np.ndarray, thr: float) -> Sim3 | None:
        """The best-scoring minimal-sample hypothesis (MSAC), or None when every sample was degenerate."""
        n, c = len(a), self.conf
        rng = np.random.default_rng(c["seed"])
        chunk = max(1, min(256, _CHUNK // n))  # small chunks: adaptive stopping can cut sampling short
        best_cost, best, best_count, drawn, needed = np.inf, None, 0, 0, c["iterations"]
        while drawn < min(needed, c["iterations"]):
            k = min(chunk, c["iterations"] - drawn)
            idx = rng.integers(0, n, size=(k, 3))
            drawn += k
            idx = idx[(idx[:, 0] != idx[:, 1]) & (idx[:, 0] != idx[:, 2]) & (idx[:, 1] != idx[:, 2])]
            s, R, t, spread = _fit_batch(a[idx], b[idx], np.ones(idx.shape), c["with_scale"])
            ok = (spread > _SAMPLE_TOL) & np.isfinite(s) & (s > 0)
            if not ok.any():
                continue
            r = _residuals(s[ok], R[ok], t[ok], a, b)
            cost = (np.minimum(r, thr) ** 2).sum(axis=1)
            i = int(np.argmin(cost))
            if cost[i] < best_cost:
                best_cost, best = cost[i], Sim3(s[ok][i], R[ok][i], t[ok][i])
                best_count = int((r[i] < thr).sum())
                needed = _iterations_needed(best_count / n, c["confidence"])
        return best

    def _refine(self, a: np.ndarray, b: np.ndarray, model: Sim3, thr: float) -> Sim3:
        """Iteratively reweighted Umeyama on the current inliers; stops early once the inlier set is stable."""
        mask = None
        for _ in range(self.conf["refine_iterations"]):
            r = _residuals(np.array([model.s]), model.R[None], model.t[None], a, b)[0]
            new_mask = r < thr
            if new_mask.sum() < 3:
                break
            w = _robust_weights(r[new_mask], thr / 2.0, self.conf["loss"])
            try:
                model = umeyama(a[new_mask], b[new_mask], self.conf["with_scale"], w)
            except ConfigError:
                break
            if mask is not None and np.array_equal(mask, new_mask):
                break
            mask = new_mask
        return model


def _iterations_needed(inlier_ratio: float, confidence: float) -> float:
    """Samples of 3 needed to draw one all-inlier sample with probability ``confidence``."""
    p = inlier_ratio ** 3
    if p >= 1.0:
        return 1.0
    if p <= 0.0:
        return math.inf
    return math.log(1.0 - confidence) / math.log(1.0 - p)


def ransac_sim3(src: np.ndarray, dst: np.ndarray, conf: dict[str, Any] | None = None
                ) -> tuple[Sim3, np.ndarray] | None:
    """``Sim3Ransac(conf)(src, dst)``: the similarity ``dst ~ T.apply(src)`` and its inliers, or None.

    Args:
        src: ``(n, 3)`` points.
        dst: ``(n, 3)`` matching points.
        conf: overrides of ``Sim3Ransac.default_conf``.

    Raises:
        ConfigError: a bad conf value, or malformed arrays.
    """
    return Sim3Ransac(conf)(src, dst)
