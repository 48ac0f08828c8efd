"""cae_lcd.fleet.overlap: the consecutive-match rule, and 3D-3D correspondences from real KITTI 00 images. Robot A has frames
100 and 102 (local poses: ground truth, metres), robot B frames 101 and 103 in its own map (the known similarity of
conftest: other rotation, translation and a scale of 2.5); the true edge is ``gt_100^-1 o S o b_101``."""

from __future__ import annotations

import numpy as np
import pytest

from cae_lcd.core.errors import ConfigError
from cae_lcd.fleet.overlap import OverlapRule, OverlapTracker, PointTriangulator, estimate_overlap, points_from_depth
from cae_lcd.fleet.sim3 import Sim3


@pytest.fixture(scope="module")
def scene(kitti_image, kitti_poses, kitti_sequences, known_sim3):
    """SIFT features of frames 100-103, intrinsics, A's and B's local poses and the true relative edge."""
    from retrieval.sequences import read_kitti_calib
    from verify.features import SIFT

    sift = SIFT()
    feats = {f: sift.extract(kitti_image("00", f)) for f in (100, 101, 102, 103)}
    gt = {f: Sim3.from_pose(p) for f, p in enumerate(kitti_poses("00"))}
    b_local = {f: Sim3(1.0, (b := known_sim3.inverse().compose(gt[f])).R, b.t) for f in (101, 103)}
    truth = gt[100].inverse().compose(known_sim3).compose(b_local[101])
    poses = {100: gt[100].matrix(), 102: gt[102].matrix(), 101: b_local[101].matrix(), 103: b_local[103].matrix()}
    return {"feats": feats, "K": read_kitti_calib(kitti_sequences / "00" / "calib.txt"), "poses": poses,
            "truth": truth, "shape": kitti_image("00", 100).shape}


@pytest.fixture(scope="module")
def triangulated(scene):
    tri, f, p, K = PointTriangulator(), scene["feats"], scene["poses"], scene["K"]
    return tri(f[100], p[100], f[102], p[102], K), tri(f[101], p[101], f[103], p[103], K)


@pytest.fixture(scope="module")
def cross_pairs(scene):
    from verify.verifier import create_verifier

    v = create_verifier().verify(scene["feats"][100], [scene["feats"][101]], scene["K"])[0]
    return v.pairs[v.geometry.mask]


class TestOverlapRule:
    def test_accepts_on_the_third_consecutive_match(self):
        rule = OverlapRule(3)
        assert [rule.update(k, m) for k, m in [(10, 4), (11, 5), (12, 6), (13, 7)]] == [False, False, True, False]
        assert rule.accepted == [(10, 4), (11, 5), (12, 6)]

    def test_a_miss_or_a_match_elsewhere_restarts_the_run(self):
        rule = OverlapRule(3, max_match_gap=5)
        assert not any(rule.update(k, m) for k, m in [(1, 4), (2, 5), (3, None), (4, 6), (5, 7), (6, 90)])
        assert rule.run == [(6, 90)] and rule.accepted is None
        assert [rule.update(7, 91), rule.update(8, 93)] == [False, True]

    @pytest.mark.parametrize("required", [1, 5])
    def test_the_count_is_configurable(self, required):
        rule = OverlapRule(required, None)
        hits = [rule.update(k, 1000 * k) for k in range(6)]
        assert hits.index(True) == required - 1


class TestOverlapTracker:
    def test_pairs_are_tracked_apart(self):
        tracker = OverlapTracker()
        assert tracker.update("B", 0, {"A": 10, "C": 3}) == []
        assert tracker.update("B", 1, {"A": 11}) == []  # C missed: its run restarts
        assert tracker.update("B", 2, {"A": 12, "C": 4}) == ["A"]
        assert tracker.accepted("A", "B") and not tracker.accepted("B", "C")

    def test_accept_marks_both_directions(self):
        t = OverlapTracker()
        t.accept("A", "B")
        assert t.accepted("A", "B") and t.accepted("B", "A") and not t.accepted("A", "C")
        assert t.update("B", 7, {"A": 3}) == []  # already accepted: no second acceptance

    def test_a_pair_may_need_a_longer_run(self):
        """The calibrated rule asks per pair for the run its robots' calibrations need (``required``, per other
        robot): B-A needs 5 here, B-C the conf's 3."""
        tracker = OverlapTracker()
        accepted = [tracker.update("B", k, {"A": 10 + k, "C": 20 + k}, {"A": 5}) for k in range(5)]
        assert accepted == [[], [], ["C"], [], ["A"]]

    def test_own_robot_is_ignored(self):
        tracker = OverlapTracker({"required": 1})
        assert tracker.update("A", 0, {"A": 0}) == []

    def test_bad_conf_is_refused(self):
        with pytest.raises(ConfigError, match="overlap.required"):
            OverlapTracker({"required": 0})
        assert set(OverlapTracker.default_conf) == set(OverlapTracker.conf_rules)


class TestPointsFromDepth:
    def test_back_projection_inverts_projection(self, triangulated, scene):
        """A depth map holding the triangulated points' z at their pixels gives the points back."""
        pts = triangulated[0]
        ok = np.isfinite(pts[:, 0])
        px = scene["feats"][100].keypoints
        depth = np.zeros(scene["shape"])
        depth[np.rint(px[ok, 1]).astype(int), np.rint(px[ok, 0]).astype(int)] = pts[ok, 2]
        back = points_from_depth(px, depth, scene["K"])
        assert np.isfinite(back[:, 0]).sum() >= ok.sum() - 2  # two features may share a pixel
        close = ok & np.isfinite(back[:, 0])
        assert np.abs(back[close] - pts[close]).max() < 0.02 * np.abs(pts[close]).max()

    def test_unknown_depth_gives_nan(self, scene):
        depth = np.full((10, 20), 5.0)
        depth[0, 0], depth[0, 1], depth[0, 2] = 0.0, np.nan, -1.0
        px = np.array([[0, 0], [1, 0], [2, 0], [25, 3], [-3, 3], [5.2, 4.4]])
        out = points_from_depth(px, depth, scene["K"])
        assert np.isnan(out[:5]).all() and out[5, 2] == 5.0
        assert points_from_depth(np.zeros((0, 2)), depth, scene["K"]).shape == (0, 3)

    def test_bad_input_is_refused(self, scene):
        with pytest.raises(ConfigError, match="depth map"):
            points_from_depth(np.zeros((1, 2)), np.zeros((2, 2, 3)), scene["K"])
        with pytest.raises(ConfigError, match="intrinsics"):
            points_from_depth(np.zeros((1, 2)), np.zeros((2, 2)), np.eye(2))


class TestPointTriangulator:
    def test_points_are_in_front_and_plausible(self, triangulated, scene):
        for pts, frame in zip(triangulated, (100, 101)):
            ok = np.isfinite(pts[:, 0])
            assert ok.sum() >= 30
            assert (pts[ok, 2] > 0).all()
        a_depth = np.median(triangulated[0][np.isfinite(triangulated[0][:, 0]), 2])
        b_depth = np.median(triangulated[1][np.isfinite(triangulated[1][:, 0]), 2])
        assert 3.0 < a_depth < 60.0 and b_depth == pytest.approx(a_depth / 2.5, rel=0.3)  # B's map is 2.5x smaller

    def test_triangulation_recovers_known_points(self, scene, kitti_landmarks):
        """Real poses, exact projections of points in front of camera 100: triangulated back within 1e-6."""
        K, p = scene["K"], scene["poses"]
        a, b = Sim3.from_pose(p[100]), Sim3.from_pose(p[102])
        world = a.apply(np.array([[-3.0, 1.0, 10.0], [4.0, -2.0, 15.0], [0.5, 0.2, 8.0]]))
        proj = [((T.inverse().apply(world)) @ K.T) for T in (a, b)]
        px = [q[:, :2] / q[:, 2:] for q in proj]
        X = PointTriangulator({"min_parallax_deg": 0.1}).triangulate(px[0], px[1], p[100], p[102], K)
        np.testing.assert_allclose(X, a.inverse().apply(world), atol=1e-6)
        assert np.isnan(PointTriangulator().triangulate(px[0], px[1] + 20, p[100], p[102], K)).all()

    def test_low_parallax_points_are_dropped(self, scene):
        """A point 300 m ahead seen from 0.84 m apart: its depth is not measurable, so no point (default 1 deg)."""
        K, p = scene["K"], scene["poses"]
        a, b = Sim3.from_pose(p[100]), Sim3.from_pose(p[102])
        world = a.apply(np.array([[5.0, 1.0, 300.0], [-3.0, 1.0, 10.0]]))
        px = [(q := T.inverse().apply(world) @ K.T)[:, :2] / q[:, 2:] for T in (a, b)]
        X = PointTriangulator().triangulate(px[0], px[1], p[100], p[102], K)
        assert np.isnan(X[0]).all() and np.isfinite(X[1]).all()


class TestEstimateOverlap:
    def test_recovers_the_relative_similarity_from_real_images(self, triangulated, cross_pairs, scene):
        rel, inliers = estimate_overlap(cross_pairs, *triangulated)
        angle, scale, trans = rel.errors(scene["truth"])
        assert angle < 2.0 and scale < 0.05 and trans < 1.0 and inliers.sum() >= 8

    def test_with_a_depth_map_on_one_side(self, triangulated, cross_pairs, scene):
        pts_b = triangulated[1]
        ok = np.isfinite(pts_b[:, 0])
        px = scene["feats"][101].keypoints
        depth = np.zeros(scene["shape"])
        depth[np.rint(px[ok, 1]).astype(int), np.rint(px[ok, 0]).astype(int)] = pts_b[ok, 2]
        rel, _ = estimate_overlap(cross_pairs, triangulated[0], points_from_depth(px, depth, scene["K"]))
        angle, scale, _ = rel.errors(scene["truth"])
        assert angle < 2.0 and scale < 0.05

    def test_no_3d_points_gives_none(self, triangulated, cross_pairs):
        nothing = np.full_like(triangulated[1], np.nan)
        assert estimate_overlap(cross_pairs, triangulated[0], nothing) is None
        assert estimate_overlap(np.zeros((0, 2)), *triangulated) is None
