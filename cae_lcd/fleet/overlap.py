"""Where two robots saw the same place: the "n consecutive matching keyframes" acceptance rule, and the 3D-3D
correspondences of a verified match from which ``ransac_sim3`` estimates the similarity between the two maps.

- ``OverlapRule``: one robot pair's state. Every keyframe the querying robot sends either matched a keyframe of the
  other robot (verified) or did not; an overlap is accepted once ``required`` consecutive keyframes matched (and
  their matches lie within ``max_match_gap`` keyframe ids of each other: the same stretch of road). The state is
  kept in memory; after a restart a run starts again (accepted overlaps are in the store).
- ``OverlapTracker``: the rules of all pairs.
- ``points_from_depth``: a keyframe's 3D feature points in its camera frame from a depth map (back-projection).
- ``PointTriangulator``: the same from the robot's own neighbouring keyframe (SIFT matches checked by the essential
  matrix, ``cv2.triangulatePoints`` with the two local poses, kept where the parallax and reprojection are good).
- ``estimate_overlap``: matched features with 3D on both sides -> ``ransac_sim3`` -> the relative similarity
  ``node_a^-1 o node_b`` (maps keyframe b's camera points to keyframe a's; ``cae_lcd.fleet.graph``'s edge convention).

Points are ``(N, 3)`` per keyframe feature, NaN where a feature has no 3D point; pixels are ``(N, 2)`` (x, y).
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from cae_lcd.core.checks import check_intrinsics
from cae_lcd.core.conf import ConfigError, Float, Int, configure
from verify.features import Features
from verify.verifier import create_verifier

from .sim3 import Sim3, Sim3Ransac

__all__ = ["OverlapRule", "OverlapTracker", "points_from_depth", "PointTriangulator", "estimate_overlap"]

log = logging.getLogger(__name__)


@dataclass
class OverlapRule:
    """The acceptance rule of one (querying robot, other robot) pair.

    Attributes:
        required: consecutive matching keyframes that accept the overlap (the paper: 3).
        max_match_gap: largest id difference between the other robot's keyframes matched by consecutive queries
            (None: any).
        run: ``(query keyframe, matched keyframe)`` of the current run of consecutive matches.
        accepted: the run that accepted the overlap, once it happened (it stays accepted).
    """

    required: int = 3
    max_match_gap: int | None = 20
    run: list[tuple[int, int]] = field(default_factory=list)
    accepted: list[tuple[int, int]] | None = None

    def update(self, keyframe: int, match: int | None, required: int | None = None) -> bool:
        """Records the querying robot's next keyframe and its verified match (None: no match); ``required``: the
        consecutive matches that accept now, if not ``self.required`` (the robots' calibrations may ask more).

        Returns:
            True when this keyframe completes the first accepted run.
        """
        required = self.required if required is None else int(required)
        if match is None:
            self.run = []
            return False
        if self.run and self.max_match_gap is not None and abs(match - self.run[-1][1]) > self.max_match_gap:
            self.run = []  # a match elsewhere: a new run starts with it
        self.run.append((int(keyframe), int(match)))
        if self.accepted is None and len(self.run) >= required:
            self.accepted = list(self.run[-required:])
            return True
        return False


class OverlapTracker:
    """``OverlapRule`` per ordered robot pair, created when a pair first matches."""

    default_conf: dict[str, Any] = {
        "required": 3,  # consecutive matching keyframes that accept an overlap between two robots
        "max_match_gap": 20,  # consecutive matches must hit keyframes this close (ids) in the other robot; null: any
    }
    conf_rules: dict[str, Any] = {"required": Int(1), "max_match_gap": Int(0, optional=True)}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "overlap")
        self.rules: dict[tuple[str, str], OverlapRule] = {}

    def update(self, robot: str, keyframe: int, matches: Mapping[str, int],
               required: Mapping[str, int] | None = None, among: Collection[str] | None = None) -> list[str]:
        """Records ``robot``'s keyframe and its best verified match in each other robot (absent: no match);
        ``required``: per other robot, the consecutive matches that accept (absent: ``required`` of the conf);
        ``among``: the other robots the keyframe was matched against (None: all; the rules of the others are left
        as they are: a catch-up replays one robot's earlier keyframes against some robots only).

        Returns:
            The other robots whose overlap with ``robot`` this keyframe accepted.
        """
        accepted = []
        for other in set(matches) - {robot}:
            self.rules.setdefault((robot, other), OverlapRule(self.conf["required"], self.conf["max_match_gap"]))
        for (query, other), rule in self.rules.items():
            if query != robot or (among is not None and other not in among):
                continue
            if rule.update(keyframe, matches.get(other), (required or {}).get(other)):
                accepted.append(other)
        return sorted(accepted)

    def accept(self, robot: str, other: str) -> None:
        """Marks the pair's overlap accepted in both directions (e.g. one stored before a restart)."""
        for key in ((robot, other), (other, robot)):
            rule = self.rules.setdefault(key, OverlapRule(self.conf["required"], self.conf["max_match_gap"]))
            rule.accepted = rule.accepted or []

    def accepted(self, robot: str, other: str) -> bool:
        """Whether an overlap of either robot with the other was accepted."""
        return any(r.accepted is not None for key in ((robot, other), (other, robot)) if (r := self.rules.get(key)))


def points_from_depth(pixels: np.ndarray, depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Back-projects pixels with the depth at their nearest pixel: ``z * K^-1 [x, y, 1]``.

    Args:
        pixels: ``(N, 2)`` x, y in the depth map's pixel grid (the image's).
        depth: ``(H, W)`` depth along the optical axis (z), in the robot's map units; 0, negative or NaN: unknown.
        K: ``(3, 3)`` intrinsics.

    Returns:
        ``(N, 3)`` points in the camera frame, NaN rows where the depth is unknown or the pixel outside the map.

    Raises:
        ConfigError: a depth map that is not 2D, pixels not ``(N, 2)``, or bad intrinsics.
    """
    K = check_intrinsics(K)
    px = np.asarray(pixels, np.float64).reshape(-1, 2) if np.size(pixels) else np.zeros((0, 2))
    d = np.asarray(depth, np.float64)
    if d.ndim != 2:
        raise ConfigError(f"a depth map is a (H, W) array; got shape {d.shape}")
    col, row = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
    inside = (col >= 0) & (col < d.shape[1]) & (row >= 0) & (row < d.shape[0])
    z = np.full(len(px), np.nan)
    z[inside] = d[row[inside], col[inside]]
    z[~(z > 0) | ~np.isfinite(z)] = np.nan
    rays = np.c_[px, np.ones(len(px))] @ np.linalg.inv(K).T
    return rays * z[:, None]


class PointTriangulator:
    """A keyframe's 3D feature points from its robot's neighbouring keyframe and the two local poses.

    Features are matched (ratio test) and checked by the essential matrix (``verify``), then triangulated
    (``cv2.triangulatePoints``); a point is kept when it lies in front of both cameras, reprojects within
    ``max_reprojection_px`` in both images and its two viewing rays differ by at least ``min_parallax_deg``.
    """

    default_conf: dict[str, Any] = {
        "max_reprojection_px": 2.0,  # largest reprojection error of a kept point, pixels, in both images
        "min_parallax_deg": 1.0,  # smallest angle between the two viewing rays of a kept point (depth precision)
    }
    conf_rules: dict[str, Any] = {"max_reprojection_px": Float(0, lo_open=True), "min_parallax_deg": Float(0, 90)}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "triangulation")
        self.verifier = create_verifier()

    def __call__(self, features: Features, pose: np.ndarray, neighbour: Features, neighbour_pose: np.ndarray,
                 K: np.ndarray) -> np.ndarray:
        """3D points of ``features`` in their camera's frame (the robot's map units).

        Args:
            features: the keyframe's features.
            pose: its ``(3, 4)``/``(4, 4)`` camera-to-map pose.
            neighbour: features of a neighbouring keyframe of the same robot (same camera).
            neighbour_pose: its pose in the same map.
            K: ``(3, 3)`` intrinsics.

        Returns:
            ``(len(features), 3)``, NaN rows for features without a good 3D point.
        """
        out = np.full((len(features), 3), np.nan)
        if not len(features) or not len(neighbour):
            return out
        v = self.verifier.verify(features, [neighbour], check_intrinsics(K))[0]
        pairs = v.pairs[v.geometry.mask] if v.inliers > 0 else np.zeros((0, 2), np.int64)
        if len(pairs):
            out[pairs[:, 0]] = self.triangulate(features.keypoints[pairs[:, 0]], neighbour.keypoints[pairs[:, 1]],
                                                pose, neighbour_pose, K)
        return out

    def triangulate(self, px_a: np.ndarray, px_b: np.ndarray, pose_a: np.ndarray, pose_b: np.ndarray,
                    K: np.ndarray) -> np.ndarray:
        """Triangulates matched pixels ``(m, 2)`` of two views -> ``(m, 3)`` in camera a's frame, NaN if rejected."""
        K = check_intrinsics(K)
        b_from_a = Sim3.from_pose(pose_b).inverse().compose(Sim3.from_pose(pose_a))
        P_a = K @ np.c_[np.eye(3), np.zeros(3)]
        P_b = K @ b_from_a.matrix()[:3]
        a = np.asarray(px_a, np.float64).reshape(-1, 2)
        b = np.asarray(px_b, np.float64).reshape(-1, 2)
        if not len(a):
            return np.zeros((0, 3))
        X = cv2.triangulatePoints(P_a, P_b, a.T, b.T)
        with np.errstate(divide="ignore", invalid="ignore"):
            X = (X[:3] / X[3]).T
            in_b = b_from_a.apply(X)
            err_a = np.linalg.norm((X @ K.T)[:, :2] / X[:, 2:] - a, axis=1)
            err_b = np.linalg.norm((in_b @ K.T)[:, :2] / in_b[:, 2:] - b, axis=1)
            centre_b = b_from_a.inverse().t
            ray_b = X - centre_b
            cos = (X * ray_b).sum(1) / (np.linalg.norm(X, axis=1) * np.linalg.norm(ray_b, axis=1))
        c = self.conf
        ok = (X[:, 2] > 0) & (in_b[:, 2] > 0) & (err_a < c["max_reprojection_px"]) & \
             (err_b < c["max_reprojection_px"]) & (cos < np.cos(np.radians(c["min_parallax_deg"])))
        X[~ok] = np.nan
        return X


def estimate_overlap(pairs: np.ndarray, points_a: np.ndarray, points_b: np.ndarray,
                     conf: dict[str, Any] | None = None) -> tuple[Sim3, np.ndarray] | None:
    """The similarity between two matched keyframes from their features' 3D points.

    Args:
        pairs: ``(M, 2)`` verified matches (feature index in keyframe a, feature index in keyframe b).
        points_a: ``(Na, 3)`` keyframe a's feature points in its camera frame (NaN: none).
        points_b: ``(Nb, 3)`` keyframe b's, in its camera frame and its robot's units.
        conf: overrides of ``Sim3Ransac.default_conf``.

    Returns:
        ``(relative, inliers (M,) bool)`` with ``relative.apply(b-camera points) ~ a-camera points`` (the edge
        ``node_a^-1 o node_b``), or None when too few matches have 3D points on both sides or RANSAC finds none.
    """
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    ok = np.flatnonzero(np.isfinite(points_a[pairs[:, 0]]).all(1) & np.isfinite(points_b[pairs[:, 1]]).all(1))
    found = Sim3Ransac(conf)(points_b[pairs[ok, 1]], points_a[pairs[ok, 0]])
    if found is None:
        log.debug("overlap: no similarity from %d of %d matches with 3D points", len(ok), len(pairs))
        return None
    inliers = np.zeros(len(pairs), bool)
    inliers[ok[found[1]]] = True
    return found[0], inliers
