"""Loop edges for a pose-graph back end: for each accepted loop, the relative pose that the verification found, with
the uncertainty its inliers actually have.

The verification (``verify.verifier``) matches the query's local features against the match's (keypoints undistorted
when the camera has a distortion model: ``geometry.distortion``), then RANSAC on the essential matrix gives ``R, t``
with ``x_match = R x_query + t`` for a point ``x`` in each camera's frame, i.e. the pose of the query camera in the
match camera's frame, refined on all its inliers (``GeometryResult.refined``: ``verify.geometry.refined_pose``).
Here it is the run's own check where the detector kept it (``LoopDetector.verified_geometry``), else computed again
with the run's own matcher and geometry settings from the keyframes' features (``LoopDetector.keyframe_features``:
the inliers of ``loops.csv`` within a few), side by side on every core; for a
calibrated run whose features are cheaper than the extractor's (``calibration.features_px``), the few edges they
give least surely (a rotation standard deviation over ``REDO_RATIO`` times the run's median, or no pose) are made
again from the extractor's own resolution read again for their frames (``edge_features``: more inliers, a more
precise pose), and the surer one kept; a resumed run gets its edges too. From two images without depth the length
of the baseline cannot be known: ``t`` is written as a unit direction and **the edge says so in its information
matrix**.

Information (``verify.geometry.pose_information``): the Gauss-Newton information of the inliers' Sampson residuals
(pixel noise estimated from the residuals themselves), in gtsam's ``Pose3`` tangent (right perturbation), divided by
``MODEL_VARIANCE`` (what the residuals of one pair cannot see: calibration, the ground-truth-free correlation of
neighbouring features; measured on KITTI 90 and the bundled sample, ``python -m bench.loop_edges``). Its rank is 5:
rotation (3) and the translation's direction (2, at the written length 1); along the translation's length it is
``UNOBSERVED_INFORMATION`` (1e-6: a standard deviation of 1000 units), so an optimiser takes the length from the rest
of the graph. The files write it in g2o's order (translation ``x y z``, then rotation), the rotation block in
radians of the rotation vector (as ``gtsam.readG2o`` reads it; g2o's own ``EdgeSE3`` measures the quaternion's
vector part, half the angle: multiply the rotation rows and columns by 2 there).

Edges in the body frame (``body_edges``, ``detect --edge-frame body``): with the camera's pose on the body ``X``
(EuRoC's ``T_BS``, the inverse of a Kalibr camchain's ``T_cam_imu``: camera -> body), the body's relative pose is
``X T X^-1`` and the information goes through the adjoint of ``X`` (a perturbation ``xi`` of the camera's pose is
``Ad_X xi`` of the body's, so every residual's chi-square is the same in both frames). Up to scale, the body's
translation is ``R_X t + (I - R_body) t_X`` at the written unit length, unobserved along ``R_X t`` (the camera's
direction turned into the body's axes): any length of the camera's baseline is a point of that line.

A metric edge (``LoopEdge.scaled``): when the baseline's length is known (stereo, depth, or the distance between the
two frames of a trajectory the caller trusts), the translation is scaled to it, its direction information divided
by the length squared and the length given its own standard deviation.
"""

from __future__ import annotations

import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, Callable, Iterable

import numpy as np

from cae_lcd.core.conf import check_choice
from verify.features import Features, create_extractor
from verify.geometry import UNOBSERVED_INFORMATION, GeometryResult, pose_information
from verify.verifier import create_verifier

__all__ = ["LoopEdge", "loop_edges", "edge_errors", "rotation_to_quaternion", "ROTATION_SIGMA_1",
           "MODEL_VARIANCE", "g2o_order", "metric_edges", "LENGTH_SIGMA", "EDGE_FRAMES", "check_edge_frame",
           "body_edges", "body_poses", "adjoint", "edge_features", "serialised", "REDO_RATIO", "PosesAhead"]

#: rotation standard deviation (radians) of one inlier, for an edge made without its residuals (no points kept):
#: ``ROTATION_SIGMA_1 / sqrt(inliers)``, translation unobserved
ROTATION_SIGMA_1 = 0.1
#: an edge made from the run's own features whose rotation standard deviation is more than this many times the
#: median of the run's edges is made again from finer ones (``loop_edges``' ``precise``): KITTI 90 through a fisheye,
#: the one edge 2.7 degrees off at 384 px said 1.1 degrees, 10x the median (``python -m bench.fisheye``)
REDO_RATIO = 2.0
#: the residuals' Gauss-Newton covariance times this is the edge's covariance: the errors of KITTI 90's edges
#: against the ground truth are this much larger (in variance) than the inliers' residuals alone predict
MODEL_VARIANCE = 70.0

#: a metric edge's standard deviation along its translation (``metric_edges``): this share of its length, at least
#: ``LENGTH_SIGMA[1]`` metres
LENGTH_SIGMA = (0.05, 0.02)

#: the frames loop edges are written in (``detect --edge-frame``): the camera's, or the body's it is mounted on
EDGE_FRAMES = ("camera", "body")

_G2O = np.r_[3, 4, 5, 0, 1, 2]  #: gtsam's order (rotation, translation) -> g2o's (translation, rotation), and back


def g2o_order(info: np.ndarray) -> np.ndarray:
    """A ``(6, 6)`` matrix in gtsam's order (rotation, translation) -> g2o's (translation, rotation); the same
    permutation turns it back."""
    return np.asarray(info)[np.ix_(_G2O, _G2O)]


@dataclass(frozen=True)
class LoopEdge:
    """One loop as a relative pose: the query camera in the match camera's frame (``x_match = R x_query + t``)."""

    query: int  #: the later frame (the g2o edge's second vertex)
    match: int  #: the earlier frame it closes on (the g2o edge's first vertex)
    inliers: int  #: geometric inliers of the verification
    R: np.ndarray  #: (3, 3) rotation, query camera -> match camera
    t: np.ndarray  #: (3,) translation: a unit direction, or metres when ``metric``
    info: np.ndarray | None = None  #: (6, 6) information, g2o's order; None: the inlier rule (``information``)
    metric: bool = False  #: the translation has its metric length
    sigma_px: float = float("nan")  #: standard deviation of the inliers' Sampson residuals, pixels

    def information(self) -> np.ndarray:
        """``(6, 6)`` information matrix in g2o's order (translation x y z, then rotation vector): the residuals'
        (module doc), or, for an edge made without them, rotation ``inliers / ROTATION_SIGMA_1^2`` and the
        translation unobserved."""
        if self.info is not None:
            return np.asarray(self.info, np.float64)
        n = max(self.inliers, 1)
        return np.diag([UNOBSERVED_INFORMATION] * 3 + [n / ROTATION_SIGMA_1**2] * 3)

    def sigmas(self) -> tuple[float, float]:
        """``(rotation, translation direction)`` standard deviations, radians: the root mean marginal variance of
        the rotation vector, and of the translation across its direction divided by its length."""
        info = g2o_order(self.information())  # -> gtsam's order
        try:
            cov = np.linalg.inv(info)
        except np.linalg.LinAlgError:
            return float("inf"), float("inf")
        u = self.R.T @ self.t / max(float(np.linalg.norm(self.t)), 1e-12)  # the length direction, query frame
        across = np.eye(3) - np.outer(u, u)
        lateral = float(np.trace(across @ cov[3:, 3:] @ across)) / 2
        return (float(np.sqrt(max(np.trace(cov[:3, :3]) / 3, 0.0))),
                float(np.sqrt(max(lateral, 0.0))) / max(float(np.linalg.norm(self.t)), 1e-12))

    def quaternion(self) -> np.ndarray:
        """``(4,)`` ``qx, qy, qz, qw`` of ``R`` (g2o's order), ``qw >= 0``."""
        return rotation_to_quaternion(self.R)

    def scaled(self, length: float, sigma_length: float) -> "LoopEdge":
        """This edge with a metric translation of ``length`` metres (its direction kept), the direction's
        information divided by ``length^2`` and ``1 / sigma_length^2`` along the length (metres)."""
        if not (length > 0 and sigma_length > 0):
            raise ValueError(f"length and sigma_length must be > 0; got {length}, {sigma_length}")
        unit = self.t / np.linalg.norm(self.t)
        info = g2o_order(self.information())
        S = np.diag([1.0, 1.0, 1.0] + [1.0 / (length * float(np.linalg.norm(self.t)))] * 3)  # unit -> metres
        info = S @ info @ S
        u = np.r_[np.zeros(3), self.R.T @ unit]
        keep = np.eye(6) - np.outer(u, u)
        info = keep @ info @ keep + np.outer(u, u) / sigma_length**2
        return replace(self, t=unit * length, info=g2o_order(info), metric=True)


def check_edge_frame(frame: str) -> str:
    """``frame`` when it is one of ``EDGE_FRAMES`` (else ``ConfigError``)."""
    return check_choice(frame, EDGE_FRAMES, "--edge-frame")


def adjoint(X: np.ndarray) -> np.ndarray:
    """``(6, 6)`` adjoint of the pose ``X`` ``(4, 4)`` in gtsam's order (rotation, translation):
    ``X exp(xi) X^-1 = exp(Ad_X xi)``, ``Ad_X = [[R, 0], [[t]x R, R]]``."""
    R, t = np.asarray(X, np.float64)[:3, :3], np.asarray(X, np.float64)[:3, 3]
    skew = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.block([[R, np.zeros((3, 3))], [skew @ R, R]])


def body_edges(edges: list[LoopEdge], T_body_camera: np.ndarray) -> list[LoopEdge]:
    """``edges`` (the query camera in the match camera's frame) as the query body in the match body's frame
    (module doc): ``X T X^-1`` with ``X = T_body_camera`` ``(4, 4)`` (camera -> body), the information through the
    adjoint (``Ad_X^-T info Ad_X^-1``, in g2o's order as written)."""
    X = np.asarray(T_body_camera, np.float64)
    Xinv = np.linalg.inv(X)
    A_inv = np.linalg.inv(adjoint(X))
    out = []
    for e in edges:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = e.R, e.t
        B = X @ T @ Xinv
        info = A_inv.T @ g2o_order(e.information()) @ A_inv
        out.append(replace(e, R=B[:3, :3], t=B[:3, 3], info=g2o_order(0.5 * (info + info.T))))
    return out


def body_poses(poses: np.ndarray | None, T_body_camera: np.ndarray) -> np.ndarray | None:
    """Camera-to-world ``poses`` ``(n, 3, 4)`` as the body's (``T_WC X^-1``, ``X = T_body_camera``); None stays."""
    if poses is None:
        return None
    return np.asarray(poses, np.float64) @ np.linalg.inv(np.asarray(T_body_camera, np.float64))


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
               conf: dict[str, Any], workers: int = 1, precise: Callable[[int], Features] | None = None,
               verified: Callable[[int, int], GeometryResult | None] | None = None) -> list[LoopEdge]:
    """The relative pose of each loop, from the keyframes' local features.

    Args:
        features: a keyframe's local features by frame id (``LoopDetector.keyframe_features``).
        loops: ``(query, match)`` frame id pairs (``(L, 2)``), as ``RunFolder.write_tables`` returns them.
        K: ``(3, 3)`` intrinsics; None: no edges (without intrinsics the geometry is a fundamental matrix, no pose).
        conf: the run's resolved conf (its ``matcher`` and ``geometry`` sections are used).
        workers: threads computing edges side by side (OpenCV and the matcher release the GIL; the same edges in
            the same order), where ``features`` (and ``precise``) may be called from several threads at once
            (``edge_features``'s and ``serialised``'s may; a ``LoopDetector``'s own may not: 1, or wrap it).
        precise: a loop frame's features at a finer resolution (``edge_features``), for the edges ``features``
            give least surely: an edge with no pose, or whose rotation standard deviation is more than
            ``REDO_RATIO`` times the median of this run's edges, is made again from them, and the one with the
            surer rotation kept (the extraction a loop frame costs is paid only for those).
        verified: the geometry the run's own check found for a ``(query, match)`` pair from ``features``
            (``LoopDetector.verified_geometry``), or None where it has none: that pair is not verified again (its
            matching and RANSAC were a third of an edge's cost), the others are.

    Returns:
        One ``LoopEdge`` per loop whose essential matrix gave a pose (and its inliers an information: at least 6),
        in the order of ``loops``; ``[]`` without ``K``.
    """
    if K is None:
        return []
    loops = [(int(q), int(m)) for q, m in loops]
    made = _edges_of(features, loops, K, conf, workers, verified)
    if precise is not None:
        sigmas = [e.sigmas()[0] for e in made if e is not None]
        bar = REDO_RATIO * float(np.median(sigmas)) if sigmas else float("inf")
        redo = [i for i, e in enumerate(made) if e is None or e.sigmas()[0] > bar]
        for i, again in zip(redo, _edges_of(precise, [loops[i] for i in redo], K, conf, workers)):
            if again is not None and (made[i] is None or again.sigmas()[0] < made[i].sigmas()[0]):
                made[i] = again
    return [e for e in made if e is not None]


def _edges_of(features: Callable[[int], Features], loops: list[tuple[int, int]], K: np.ndarray,
              conf: dict[str, Any], workers: int,
              verified: Callable[[int, int], GeometryResult | None] | None = None) -> list[LoopEdge | None]:
    """``loop_edges``' edges from one source of features (the pairs ``verified`` gives a geometry not verified
    again), None where a loop gave no pose, in the order of ``loops``."""
    verifiers = threading.local()

    def edge(pair: tuple[int, int]) -> LoopEdge | None:
        q, m = pair
        geo = verified(q, m) if verified is not None else None
        if geo is None:
            if not hasattr(verifiers, "verifier"):  # one per thread
                verifiers.verifier = create_verifier(conf.get("matcher"), conf.get("geometry"))
            geo = verifiers.verifier.verify(features(q), [features(m)], K)[0].geometry
        if geo.refined is None or geo.essential is None:
            return None
        R, t = (np.asarray(v, np.float64) for v in geo.refined)
        _, a, b, K_used = geo.essential
        info, sigma_px = pose_information(a.reshape(-1, 2), b.reshape(-1, 2), K_used, R, t, MODEL_VARIANCE)
        if not np.isfinite(sigma_px):
            return None
        return LoopEdge(q, m, int(geo.inliers), R, t, g2o_order(info), sigma_px=sigma_px)

    if workers <= 1 or len(loops) < 2:
        return list(map(edge, loops))
    with ThreadPoolExecutor(min(workers, len(loops)), thread_name_prefix="loop-edges") as pool:
        return list(pool.map(edge, loops))


class PosesAhead:
    """Refines the poses of a run's loops as the run finds them (``GeometryResult.refined``, most of an edge's cost),
    on one worker thread beside the stream, so that ``loop_edges`` finds them made: the same poses (each pair's
    refinement is deterministic), computed while the stream's own threads leave a core idle rather than after the
    last frame. ``close`` (or leaving the ``with``) waits for the refinements under way. A refinement that fails here
    keeps nothing: ``loop_edges`` computes it again and meets the error itself.

    Args:
        verified: the run's own check of a ``(query, match)`` pair (``LoopDetector.verified_geometry``), None where it
            kept none (that pair's edge is made by ``loop_edges``).
    """

    def __init__(self, verified: Callable[[int, int], GeometryResult | None]) -> None:
        self._verified = verified
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="poses-ahead")

    def add(self, pairs: Iterable[tuple[int, int]]) -> None:
        """Starts refining the poses of the loops ``pairs`` (``(query, match)``)."""
        for q, m in pairs:
            geo = self._verified(q, m)
            if geo is not None and geo.essential is not None:
                self._pool.submit(getattr, geo, "refined")

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    def __enter__(self) -> "PosesAhead":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def serialised(features: Callable[[int], Features]) -> Callable[[int], Features]:
    """``features`` callable from several threads at once: one call at a time (a ``LoopDetector``'s own reads its
    store and caches), the matching that uses them still side by side (``loop_edges``' ``workers``)."""
    lock = threading.Lock()

    def get(frame_id: int) -> Features:
        with lock:
            return features(frame_id)

    return get


def edge_features(read: Callable[[int], Any], features_conf: dict[str, Any],
                  fallback: Callable[[int], Features]) -> Callable[[int], Features]:
    """Local features for the loop edges at the extractor's own resolution (``features_conf``), where a calibrated
    run detected with cheaper ones (``calibration.features_px``; ``loop_edges``' ``precise``): each frame read again
    (``read(i)``: an image, or the reason it cannot be read) and extracted once, kept in the store's form
    (``Features.compact``); a frame that cannot be read again gets ``fallback``'s (the run's own). Safe to call from
    several threads at once.

    KITTI 90 through a fisheye (``python -m bench.fisheye``): at the run's 384 px one pair's rotation was 2.7
    degrees off (138 inliers, ambiguous between the forward motion's two minima), at the extractor's 512 px 0.08
    (231 inliers).
    """
    extractors, reading = threading.local(), threading.Lock()

    @functools.lru_cache(maxsize=1024)
    def get(frame_id: int) -> Features:
        with reading:  # a sequence's reader (a video, a bag) and ``fallback`` serve one thread at a time
            image = read(frame_id)
            if not isinstance(image, np.ndarray):
                return fallback(frame_id)
        if not hasattr(extractors, "extractor"):  # one per thread: extractions side by side (``loop_edges``)
            extractors.extractor = create_extractor(features_conf)
        return extractors.extractor.extract(image).compact()

    return get


def metric_edges(edges: list[LoopEdge], poses: np.ndarray | None) -> list[LoopEdge]:
    """``edges`` made metric where ``poses`` ``(N, 3|4, 4)`` (camera-to-world, metres) give both frames a position:
    the length is the distance between them (a baseline the caller trusts: its odometry, stereo or depth), with
    ``LENGTH_SIGMA``; the direction and rotation stay the images'. Edges without both poses stay up to scale."""
    if poses is None:
        return list(edges)
    out = []
    for e in edges:
        ends = [poses[i][:3, 3] for i in (e.query, e.match) if i < len(poses) and np.isfinite(poses[i]).all()]
        length = float(np.linalg.norm(ends[0] - ends[1])) if len(ends) == 2 else 0.0
        out.append(e.scaled(length, max(LENGTH_SIGMA[0] * length, LENGTH_SIGMA[1])) if length > 1e-3 else e)
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
