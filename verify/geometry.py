"""Geometric check of putative matches: RANSAC on the essential matrix (intrinsics known) or the fundamental matrix.

numpy in, numpy out. Points are ``(M, 2)`` float pixel coordinates in the original images.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any, Callable

import cv2
import numpy as np

from cae_lcd.core.conf import Bool, Choice, ConfigError, Float, Floats, Int, configure

from .camera import COEFFICIENTS, DISTORTION_MODELS, undistort_points

__all__ = ["GeometryResult", "GeometricVerifier", "floor_iterations", "pose_information", "sampson_residuals",
           "refine_pose", "refined_pose"]

_METHODS = {"ransac": cv2.RANSAC, "lmeds": cv2.LMEDS, "magsac": cv2.USAC_MAGSAC, "usac": cv2.USAC_DEFAULT}


#: the mirror test looks for a homography that holds at least this share of a pair's inliers ...
_MIRROR_SHARE = 0.5
#: ... and finds one that exists with this probability: RANSAC needs log(1 - p) / log(1 - share^4) 4-point samples
#: (143 here) where the default cap would run 2000 on every real pair (none of which has such a homography)
_MIRROR_CONFIDENCE = 0.9999
_MIRROR_ITERS = math.ceil(math.log(1 - _MIRROR_CONFIDENCE) / math.log(1 - _MIRROR_SHARE ** 4))
#: ... by OpenCV's USAC (RANSAC with a local optimisation), among the orientation-reversing homographies only
#: (``GeometricVerifier._unmirrored``)
_MIRROR_METHOD = cv2.USAC_FAST


_UNSET = object()  #: ``_kept``'s "not computed yet" (None is a value: no essential matrix, no pose)


def _kept(fn: Callable[[Any], Any]) -> property:
    """A read-only property computed on first use and kept on the instance: ``functools.cached_property`` without its
    lock, which before Python 3.12 is one lock for every instance, so that loop edges refined on several threads
    (``retrieval.edges``) ran one at a time. Two threads that ask at once may both compute it (a deterministic value:
    the same either way); the first kept."""
    key = f"_kept_{fn.__name__}"

    @functools.wraps(fn)
    def get(self: Any) -> Any:
        got = self.__dict__.get(key, _UNSET)
        return self.__dict__.setdefault(key, fn(self)) if got is _UNSET else got

    return property(get)


@dataclass
class GeometryResult:
    inliers: int  #: number of RANSAC inliers (0 when the model could not be estimated)
    mask: np.ndarray  #: (M,) bool, True for inliers
    model: str  #: "essential", "fundamental" or "none"
    #: essential with ``recover_pose``: ``(E (3, 3), query inliers (n, 1, 2), candidate inliers (n, 1, 2), K (3, 3))``,
    #: decomposed into ``R``, ``t`` on first use (only an accepted loop needs them: ~1 ms a pair saved)
    essential: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False,
                                                                                   compare=False)
    threshold: float = 2.0  #: the check's inlier threshold, pixels (the scale of ``refined``'s robust cost)

    @_kept
    def _pose(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        if self.essential is None:
            return None, None
        E, a, b, K = self.essential
        _, R, t, _ = cv2.recoverPose(E, a, b, K)
        return R, t.ravel()

    @property
    def R(self) -> np.ndarray | None:
        """``(3, 3)`` rotation query -> candidate, RANSAC's (its best five-point sample); essential only, else None."""
        return self._pose[0]

    @property
    def t(self) -> np.ndarray | None:
        """``(3,)`` unit translation direction, RANSAC's; essential only, else None."""
        return self._pose[1]

    @_kept
    def refined(self) -> tuple[np.ndarray, np.ndarray] | None:
        """``(R (3, 3), t (3,) unit)`` refined on all the inliers (``refined_pose``: what a loop edge writes; ~10 ms
        a pair, so not for every frame's best candidate as ``R``, ``t`` are); essential only, else None."""
        if self.essential is None:
            return None
        E, a, b, K = self.essential
        return refined_pose(E, a.reshape(-1, 2), b.reshape(-1, 2), K, self.threshold)


def _skew(v: np.ndarray) -> np.ndarray:
    """``(..., 3)`` vectors -> ``(..., 3, 3)`` their cross-product matrices."""
    v = np.asarray(v, np.float64)
    out = np.zeros(v.shape + (3,))
    out[..., 0, 1], out[..., 0, 2], out[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    return out - np.swapaxes(out, -1, -2)


def sampson_residuals(xq: np.ndarray, xc: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(n,)`` signed Sampson distances of normalised homogeneous points ``xq``, ``xc`` ``(n, 3)`` to the epipolar
    geometry ``x_c^T [t]x R x_q = 0`` (``x_c = R x_q + t``), in normalised image units (times a focal length:
    pixels). Invariant to the length of ``t``. Poses may come stacked: ``R (..., 3, 3)``, ``t (..., 3)`` give
    ``(..., n)``, every pose's residuals in one product."""
    E = _skew(t) @ R
    Ex, Etx = xq @ np.swapaxes(E, -1, -2), xc @ E
    den = np.sqrt(Ex[..., 0] ** 2 + Ex[..., 1] ** 2 + Etx[..., 0] ** 2 + Etx[..., 1] ** 2)
    return np.sum(xc * Ex, axis=-1) / np.maximum(den, 1e-15)


#: the information along the translation's length (unobservable from two images): near zero, so that a back end
#: can still invert the matrix (a standard deviation of 1000 units of the unit translation)
UNOBSERVED_INFORMATION = 1e-6
_STEP = 1e-6  #: central-difference step of the Jacobian, radians and units of the unit translation
_STEPS = np.vstack([np.eye(6) * _STEP, -np.eye(6) * _STEP, np.zeros((1, 6))])  #: (13, 6) +h, -h, the pose itself
_STEP_ROTATIONS = np.stack([cv2.Rodrigues(h[:3].reshape(3, 1))[0] for h in _STEPS])  #: (13, 3, 3) their rotations


def _normalised(pts: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, float]:
    """``(n, 2)`` pixels -> ``(n, 3)`` homogeneous normalised points, and the focal length (pixels a unit)."""
    pts = np.asarray(pts, np.float64).reshape(-1, 2)
    K = np.asarray(K, np.float64)
    return np.c_[pts, np.ones(len(pts))] @ np.linalg.inv(K).T, float(np.sqrt(abs(K[0, 0] * K[1, 1])))


def _residual_jacobian(xq: np.ndarray, xc: np.ndarray, focal: float, R: np.ndarray,
                       t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inliers' Sampson residuals in pixels ``(n,)`` at the pose ``R, t`` and their Jacobian ``(n, 6)`` in the
    right-perturbed tangent ``(omega, delta)`` (``R exp(omega)``, ``t + R delta``), by central differences."""
    Rs = R @ _STEP_ROTATIONS
    r = focal * sampson_residuals(xq, xc, Rs, t + _STEPS[:, 3:] @ R.T)  # (13, n): every perturbed pose at once
    return r[12], ((r[:6] - r[6:12]) / (2 * _STEP)).T


def _along(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """``(6,)`` the translation's length direction in the tangent (unobservable from two images)."""
    return np.r_[np.zeros(3), R.T @ t / np.linalg.norm(t)]


def pose_information(pts_q: np.ndarray, pts_c: np.ndarray, K: np.ndarray, R: np.ndarray,
                     t: np.ndarray, variance_factor: float = 1.0) -> tuple[np.ndarray, float]:
    """The information of a relative pose from its inliers' epipolar residuals: what these points say about it.

    The pose is perturbed on the right, as gtsam's ``Pose3`` (``T exp(xi)``, ``xi = (omega, delta)``: rotation
    ``R exp(omega)``, translation ``t + R delta``, i.e. both in the query camera's frame), at the translation's
    written length ``|t|``. The Sampson residual of each inlier, in pixels, is differentiated numerically (``J``,
    ``(n, 6)``) and the pixel noise estimated from the residuals themselves (``s^2 = sum r^2 / (n - 5)``: five
    degrees of freedom are fitted), giving the Gauss-Newton information ``J^T J / s^2``. Its rank is 5: the
    residuals do not change along the translation's length, where ``UNOBSERVED_INFORMATION`` is put.

    Args:
        pts_q: ``(n, 2)`` inlier pixel coordinates (undistorted) in the query image.
        pts_c: ``(n, 2)`` the same inliers' coordinates in the match image.
        K: ``(3, 3)`` intrinsics of both.
        R: ``(3, 3)`` the pose's rotation (``x_c = R x_q + t``).
        t: ``(3,)`` its translation.
        variance_factor: the covariance is multiplied by this (errors the residuals do not see).

    Returns:
        ``(info (6, 6) in gtsam's order rotation then translation, s the residuals' standard deviation in pixels)``;
        with fewer than 6 points, or a degenerate configuration, ``(zeros, nan)``.
    """
    n = len(pts_q)
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)
    if n < 6 or not np.linalg.norm(t) > 0:
        return np.zeros((6, 6)), float("nan")
    xq, focal = _normalised(pts_q, K)
    xc, _ = _normalised(pts_c, K)
    r0, J = _residual_jacobian(xq, xc, focal, R, t)
    s2 = float(r0 @ r0) / (n - 5)
    if not (np.isfinite(J).all() and s2 > 0):
        return np.zeros((6, 6)), float("nan")
    info = J.T @ J / (s2 * variance_factor)
    along = _along(R, t)
    keep = np.eye(6) - np.outer(along, along)
    info = keep @ info @ keep + UNOBSERVED_INFORMATION * np.outer(along, along)
    return 0.5 * (info + info.T), float(np.sqrt(s2))


_REFINE_ITERATIONS = 20  #: Gauss-Newton steps of the pose refinement at most
_REFINE_HALVINGS = 8  #: step halvings tried when a full step does not lower the cost
#: the refinement stops when a step lowers the cost by less than this share of it: KITTI 90's 204 refinements
#: (its loop edges, two starts each) take 5.1 steps instead of 9.2 at 1e-9, their rotations 0.001 degree and their
#: directions 0.03 degree from where 1e-9 stops (the edges' own standard deviations are ~0.05 and ~1 degree)
_REFINE_TOL = 1e-5


def _cauchy_cost(r: np.ndarray, scale: float) -> float:
    """The robust cost ``sum log(1 + (r / scale)^2)`` of residuals ``r`` (a few bad matches weigh little)."""
    return float(np.sum(np.log1p((r / scale) ** 2)))


def refine_pose(pts_q: np.ndarray, pts_c: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, float]:
    """The relative pose ``R, t`` refined on all its inliers: iteratively reweighted Gauss-Newton on their Sampson
    residuals (pixels) with a Cauchy cost of ``scale`` pixels, in the tangent of ``pose_information`` less the
    translation's length (5 degrees of freedom: rotation and the unit translation's direction).

    RANSAC's pose is the exact solution of its best five-point sample: on KITTI 90's loops its rotation is 0.16
    degree off the ground truth (median) and the refined one 0.05 (``python -m bench.fisheye``).

    Args:
        pts_q: ``(n, 2)`` the inliers' pixel coordinates (undistorted) in the query image.
        pts_c: ``(n, 2)`` the same inliers' coordinates in the match image.
        K: ``(3, 3)`` intrinsics of both.
        R: ``(3, 3)`` the starting rotation (``x_c = R x_q + t``).
        t: ``(3,)`` the starting translation (any length).
        scale: the robust cost's scale, pixels.

    Returns:
        ``(R (3, 3), t (3,) unit, cost)``: the cost (``_cauchy_cost``) never higher than the start's; the start
        itself with fewer than 6 points.
    """
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64).reshape(3)
    t = t / np.linalg.norm(t)
    xq, focal = _normalised(pts_q, K)
    xc, _ = _normalised(pts_c, K)
    cost = _cauchy_cost(focal * sampson_residuals(xq, xc, R, t), scale)
    if len(xq) < 6:
        return R, t, cost
    for _ in range(_REFINE_ITERATIONS):
        r, J = _residual_jacobian(xq, xc, focal, R, t)
        w = 1.0 / (1.0 + (r / scale) ** 2)  # the Cauchy cost's weights
        u = _along(R, t)
        keep = np.eye(6) - np.outer(u, u)
        A, g = keep @ (J.T * w) @ J @ keep, keep @ (J.T @ (w * r))
        step = -np.linalg.lstsq(A, g, rcond=None)[0]
        for _ in range(_REFINE_HALVINGS):
            Rn = R @ cv2.Rodrigues(step[:3].reshape(3, 1))[0]
            tn = t + R @ step[3:]
            tn /= np.linalg.norm(tn)
            new = _cauchy_cost(focal * sampson_residuals(xq, xc, Rn, tn), scale)
            if new < cost:
                break
            step = step / 2
        else:
            break
        done = cost - new < _REFINE_TOL * max(cost, 1.0)
        R, t, cost = Rn, tn, new
        if done:
            break
    return R, t, cost


def refined_pose(E: np.ndarray, pts_q: np.ndarray, pts_c: np.ndarray, K: np.ndarray,
                 threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """The pose of an essential matrix's inliers: RANSAC's ``E`` and MAGSAC's on the same inliers each decomposed
    (``cv2.recoverPose``) and refined (``refine_pose``, scale ``threshold / 2``), the one of lower cost kept.

    Two starts because a forward-moving camera's epipolar geometry has a second minimum where a sideways translation
    and a turned rotation explain the inliers about as well: RANSAC's sample lands in it now and then (KITTI 90 seen
    through a fisheye: one loop 1.8 degrees off, its refinement stays there) and a second estimator rarely does.

    Args:
        E: ``(3, 3)`` RANSAC's essential matrix.
        pts_q: ``(n, 2)`` its inliers in the query image (undistorted pixels).
        pts_c: ``(n, 2)`` the same inliers in the match image.
        K: ``(3, 3)`` intrinsics.
        threshold: the check's inlier threshold, pixels.

    Returns:
        ``(R (3, 3), t (3,) unit)``.
    """
    a = np.ascontiguousarray(pts_q, np.float64).reshape(-1, 1, 2)
    b = np.ascontiguousarray(pts_c, np.float64).reshape(-1, 1, 2)
    starts = [E]
    if len(a) >= 6:
        other, _ = cv2.findEssentialMat(a, b, K, method=cv2.USAC_MAGSAC, prob=0.999, threshold=threshold)
        starts += [] if other is None else [other[i:i + 3] for i in range(0, len(other) - 2, 3)]
    poses = [refine_pose(a, b, K, R, t.ravel(), threshold / 2)
             for R, t in (cv2.recoverPose(start, a, b, K)[1:3] for start in starts)]
    R, t, _ = min(poses, key=lambda pose: pose[2])
    return R, t


def floor_iterations(floor: int, matches: int, confidence: float, cap: int) -> int:
    """RANSAC's iterations for a pre-check that asks whether a pair of ``matches`` matches holds ``floor`` inliers:
    those that draw, with probability ``confidence``, one 7-point sample (F's minimal one) of inliers only where
    ``floor`` of the matches are (a pair holding more is found sooner), ``cap`` at most, at least 1; ``cap`` without a
    floor. A pair of 15 matches asked for 12 needs 30 iterations, of 20 matches 244, of 30 4300. Look-alike pairs have
    few matches (KITTI 90 streamed: three in four of a refit's null pairs 12-19, their pre-check 0.55 ms at
    ``max_iters`` 2000, 0.12 so bounded), a revisit's hundreds, whose MAGSAC stops by itself in a few iterations.

    Args:
        floor: the inliers asked for (0: none, ``cap`` returned).
        matches: the putative matches ``M``.
        confidence: the probability of drawing an all-inlier sample, in (0, 1).
        cap: the iterations at most (``max_iters``).
    """
    if floor <= 0 or matches <= 0:
        return int(cap)
    miss = 1.0 - min(floor / matches, 1.0) ** 7  # P(a 7-point sample holds an outlier)
    if miss <= 0.0:
        return 1
    return int(min(cap, max(1, math.ceil(math.log(1.0 - confidence) / math.log(miss)))))


class GeometricVerifier:
    """Estimates the two-view geometry of a match set with RANSAC and counts its inliers."""

    default_conf: dict[str, Any] = {
        "model": "auto",  # "essential" (needs intrinsics), "fundamental", "auto" (essential when K is known), "none"
        "method": "ransac",  # robust estimator: "ransac", "magsac", "usac" or "lmeds"
        "threshold": 2.0,  # max epipolar distance of an inlier, pixels of the original image
        "confidence": 0.999,  # RANSAC confidence
        "max_iters": 2000,  # RANSAC iteration cap (a pre-check with an inlier floor: ``floor_iterations``, at most)
        "recover_pose": True,  # essential only: also decompose E into R and the unit translation t
        "prefilter": True,  # essential only: first a fast fundamental-matrix MAGSAC; E runs on its inliers only
        "reject_mirrored": True,  # a pair whose inliers fit a mirror (an orientation-reversing homography) has none:
        #                           no camera motion mirrors an image, a look-alike place (or a flipped frame) can
        "distortion_model": "none",  # lens model of the keypoints (verify/camera.py): "none", "radtan" (OpenCV's
        #                              k1 k2 p1 p2 [k3..k6]) or "equidistant" (fisheye k1..k4); undistorted with K
        #                              before the check (from --camera-info, EuRoC's sensor.yaml, a bag's CameraInfo)
        "distortion_coefficients": [],  # the model's coefficients (4, 5 or 8 for radtan, 4 for equidistant)
    }
    conf_rules: dict[str, Any] = {
        "model": Choice("auto", "essential", "fundamental", "none"), "method": Choice(*_METHODS),
        "threshold": Float(0, 100, lo_open=True), "confidence": Float(0, 1, lo_open=True, hi_open=True),
        "max_iters": Int(1, 1_000_000), "recover_pose": Bool(), "prefilter": Bool(), "reject_mirrored": Bool(),
        "distortion_model": Choice(*DISTORTION_MODELS), "distortion_coefficients": Floats(-1e3, 1e3, min_len=0)}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "geometry")
        self.check_section(self.conf)

    @staticmethod
    def check_section(conf: dict[str, Any]) -> None:
        """What the rules of single values cannot check: the distortion model's coefficient count.

        Raises:
            ConfigError: a count the model does not take.
        """
        model, n = conf["distortion_model"], len(conf["distortion_coefficients"])
        if model != "none" and n not in COEFFICIENTS[model]:
            raise ConfigError(f"geometry.distortion_coefficients: the {model} model takes "
                              f"{' or '.join(map(str, COEFFICIENTS[model]))} coefficients, got {n}")

    def model_for(self, K: np.ndarray | None) -> str:
        model = self.conf["model"]
        if model == "auto":
            return "essential" if K is not None else "fundamental"
        if model == "essential" and K is None:
            raise ConfigError("geometry.model is 'essential' but no intrinsics are known (calib.txt or --intrinsics)")
        return model

    def __call__(self, pts_q: np.ndarray, pts_c: np.ndarray, K: np.ndarray | None = None,
                 min_inliers: int = 0) -> GeometryResult:
        """Verifies ``M`` matched points.

        Args:
            pts_q: ``(M, 2)`` query-image points (distorted as the camera saw them: undistorted here with ``K`` when
                the conf has a ``distortion_model``; the essential model's points are the undistorted ones).
            pts_c: ``(M, 2)`` candidate-image points (same order).
            K: ``(3, 3)`` intrinsics shared by both images, or None.
            min_inliers: with ``prefilter``, a pair whose fundamental-matrix inliers (by MAGSAC) are fewer than this
                stops there and reports that count, with ``model`` saying so: the essential matrix cannot have more;
                on the fundamental model MAGSAC's count stands for the configured estimator's under the floor. The
                pre-check then runs the iterations that find a pair holding this many inliers
                (``floor_iterations``).

        Returns:
            ``GeometryResult``; with fewer matches than the model needs (5 for E, 8 for F) ``inliers == 0``.
        """
        model = self.model_for(K)
        m = len(pts_q)
        if model == "none":
            return GeometryResult(0, np.zeros(m, bool), "none")
        if K is not None and self.conf["distortion_model"] != "none":
            dist = self.conf["distortion_model"], self.conf["distortion_coefficients"]
            pts_q, pts_c = undistort_points(pts_q, K, *dist), undistort_points(pts_c, K, *dist)
        if m < (5 if model == "essential" else 8):
            return GeometryResult(0, np.zeros(m, bool), model)
        a = np.ascontiguousarray(pts_q, np.float64).reshape(-1, 1, 2)
        b = np.ascontiguousarray(pts_c, np.float64).reshape(-1, 1, 2)
        c = self.conf
        method = _METHODS[c["method"]]
        if model == "fundamental":
            pre = self._prefilter(a, b, min_inliers) if min_inliers and method != cv2.USAC_MAGSAC else None
            if pre is not None and pre.inliers < min_inliers:  # a pair that cannot reach it stops here
                return pre
            full = self._fundamental(a, b, method)
            return self._unmirrored(full, a, b) if full is not None else GeometryResult(0, np.zeros(m, bool), model)
        subset = np.arange(m)
        pre = self._prefilter(a, b, min_inliers)
        if pre is not None:  # E's inliers are (up to the threshold's definition) a subset of the best F's
            if pre.inliers < max(min_inliers, 5):
                return pre
            pre = self._unmirrored(pre, a, b)
            if not pre.inliers:
                return pre
            subset = np.flatnonzero(pre.mask)
        try:
            E, mask = cv2.findEssentialMat(a[subset], b[subset], K, method=method, prob=c["confidence"],
                                           threshold=c["threshold"], maxIters=c["max_iters"])
        except cv2.error:  # as ``_fundamental``: no model
            E = mask = None
        if E is None or mask is None:
            return GeometryResult(0, np.zeros(m, bool), model)
        E = E[:3]  # several solutions come stacked as (3k, 3): the mask belongs to the first
        inl = np.zeros(m, bool)
        inl[subset[mask.ravel().astype(bool)]] = True
        essential = (E, a[inl], b[inl], K) if c["recover_pose"] and inl.sum() >= 5 else None
        return GeometryResult(int(inl.sum()), inl, model, essential, c["threshold"])

    def _unmirrored(self, res: GeometryResult, a: np.ndarray, b: np.ndarray) -> GeometryResult:
        """``res``, or no inliers where most of them fit one orientation-reversing homography (``reject_mirrored``).

        Two views of a scene by a real camera never mirror each other: a plane's homography between them keeps the
        orientation of the image (points in front of both cameras), so its local Jacobian ``det(H) / w^3`` is
        positive. An epipolar model is blind to a mirror (a left-right flip is an affine map, which any fundamental
        matrix of a degenerate pair explains), so a mirrored look-alike would pass with many inliers.

        The search runs on the candidate's points mirrored (``x -> -x``, an isometry: every homography's inliers are
        those of the mirrored one, ``diag(-1, 1, 1) H``, whose orientation is the reverse), by OpenCV's USAC, which
        keeps only orientation-preserving homographies: it looks among exactly the orientation-reversing ones of the
        pair itself, and on a real pair, which has none, gives up at once (0.02 ms against 1.9 ms for ``cv2.RANSAC``
        fitting every homography and then reading its orientation, on the bundled sample's adjacent frames).
        """
        if not self.conf["reject_mirrored"] or res.inliers < 8:
            return res
        pa, pb = a[res.mask].reshape(-1, 2), b[res.mask].reshape(-1, 2) * np.array([-1, 1], b.dtype)
        H, hmask = cv2.findHomography(pa, pb, _MIRROR_METHOD, self.conf["threshold"], maxIters=_MIRROR_ITERS,
                                      confidence=_MIRROR_CONFIDENCE)
        if H is None or hmask is None or hmask.sum() < res.inliers * _MIRROR_SHARE:
            return res
        fit = hmask.ravel().astype(bool)
        w = pa[fit] @ H[2, :2] + H[2, 2]
        if np.median(np.linalg.det(H) / w**3) > 0:  # kept by the mirrored points: reversed by the pair's own
            return GeometryResult(0, np.zeros(len(a), bool), res.model)
        return res

    def _prefilter(self, a: np.ndarray, b: np.ndarray, floor: int = 0) -> GeometryResult | None:
        """The cheap pre-check (``prefilter``): F by MAGSAC, ~10x cheaper than a RANSAC that runs to ``max_iters``
        on a bad pair (the 5-point solver costs ~0.5 ms an iteration; F by RANSAC on a plain folder's full-size
        frames made verification 2.5x dearer), with a ``floor`` the iterations that would find a pair holding it
        (``floor_iterations``); None where it is off, the points are fewer than 8, or OpenCV's MAGSAC finds no model
        to start from (it asserts on some degenerate point sets: the full check decides)."""
        if not self.conf["prefilter"] or len(a) < 8:
            return None
        c = self.conf
        iters = floor_iterations(floor, len(a), c["confidence"], c["max_iters"])
        return self._fundamental(a, b, cv2.USAC_MAGSAC, iters)

    def _fundamental(self, a: np.ndarray, b: np.ndarray, method: int, iters: int | None = None
                     ) -> GeometryResult | None:
        """F by ``method`` on ``(M, 1, 2)`` points (``iters``: the iteration cap, default ``max_iters``); None where
        OpenCV's estimator fails on the point set (its USAC estimators assert on some real ones,
        ``tests/verify/test_geometry.py``'s ``MAGSAC_ASSERTS``)."""
        c = self.conf
        try:
            F, mask = cv2.findFundamentalMat(a, b, method, c["threshold"], c["confidence"],
                                             c["max_iters"] if iters is None else iters)
        except cv2.error:
            return None
        if F is None or mask is None:
            return GeometryResult(0, np.zeros(len(a), bool), "fundamental")
        inl = mask.ravel().astype(bool)
        return GeometryResult(int(inl.sum()), inl, "fundamental")
