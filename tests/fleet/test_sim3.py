"""cae_lcd.fleet.sim3: the Sim3 type, Umeyama's closed form (against gtsam's Align and a brute-force optimality check) and
RANSAC on 3D points built from real KITTI 00 ground-truth poses, with noise and wrong matches."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from cae_lcd.core.errors import ConfigError
from cae_lcd.fleet.sim3 import Sim3, Sim3Ransac, ransac_sim3, umeyama


def cost(T: Sim3, src: np.ndarray, dst: np.ndarray) -> float:
    return float(((T.apply(src) - dst) ** 2).sum())


def rot(axis_angle) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis_angle, np.float64))[0]


class TestSim3:
    def test_matrix_and_apply_agree(self, known_sim3, kitti_landmarks):
        p = kitti_landmarks[:50]
        homog = np.c_[p, np.ones(len(p))] @ known_sim3.matrix().T
        np.testing.assert_allclose(known_sim3.apply(p), homog[:, :3], atol=1e-9)
        np.testing.assert_allclose(known_sim3.apply(p[0]), homog[0, :3], atol=1e-9)

    def test_inverse_and_compose(self, known_sim3, kitti_landmarks):
        p = kitti_landmarks[:50]
        other = Sim3(0.7, rot([0.0, 0.4, 0.1]), np.array([1.0, 2.0, 3.0]))
        np.testing.assert_allclose(known_sim3.inverse().apply(known_sim3.apply(p)), p, atol=1e-9)
        np.testing.assert_allclose(known_sim3.compose(other).apply(p), known_sim3.apply(other.apply(p)), atol=1e-9)
        np.testing.assert_allclose(known_sim3.compose(other).matrix(), known_sim3.matrix() @ other.matrix(),
                                   atol=1e-9)

    def test_from_matrix_round_trip(self, known_sim3):
        back = Sim3.from_matrix(known_sim3.matrix())
        assert back.errors(known_sim3) == pytest.approx((0, 0, 0), abs=1e-6)
        assert Sim3.from_matrix(known_sim3.matrix()[:3]).s == pytest.approx(2.5)

    def test_errors_measure_the_difference(self, known_sim3):
        tilted = Sim3(known_sim3.s * 1.02, rot([0, 0, np.radians(1.0)]) @ known_sim3.R, known_sim3.t + [0, 0, 3])
        angle, scale, trans = tilted.errors(known_sim3)
        assert angle == pytest.approx(1.0, abs=1e-6) and scale == pytest.approx(0.02) and trans == pytest.approx(3)

    def test_is_immutable(self, known_sim3):
        with pytest.raises(ValueError):
            known_sim3.R[0, 0] = 2.0

    @pytest.mark.parametrize("s, R", [(0.0, np.eye(3)), (np.nan, np.eye(3)), (1.0, np.diag([1.0, 1.0, -1.0])),
                                      (1.0, 2 * np.eye(3)), (1.0, np.eye(2))])
    def test_rejects_what_is_not_a_similarity(self, s, R):
        with pytest.raises(ConfigError):
            Sim3(s, R, np.zeros(3))

    def test_from_matrix_rejects_a_mirror(self):
        with pytest.raises(ConfigError):
            Sim3.from_matrix(np.diag([1.0, 1.0, -1.0, 1.0]))

    @pytest.mark.parametrize("value", [np.inf, np.nan, 1e300])
    def test_from_matrix_rejects_what_is_not_finite(self, value):
        """An infinite or overflowing entry (a poisoned stored transform) is refused, never turned into NaNs."""
        M = np.diag([value, value, value, 1.0])  # 1e300: finite entries, an infinite determinant
        with pytest.raises(ConfigError, match="finite"):
            Sim3.from_matrix(M)


class TestUmeyama:
    def test_exact_on_kitti_points(self, known_sim3, kitti_landmarks):
        est = umeyama(kitti_landmarks, known_sim3.apply(kitti_landmarks))
        angle, scale, trans = est.errors(known_sim3)
        assert angle < 1e-4 and scale < 1e-12 and trans < 1e-9

    def test_agrees_with_gtsam_align_on_noisy_points(self, known_sim3, kitti_landmarks):
        """Reference: gtsam's Similarity3.Align (its translation is t / s: gtsam maps x -> s (R x + t))."""
        import gtsam

        dst = known_sim3.apply(kitti_landmarks) + np.random.default_rng(0).normal(0, 0.3, kitti_landmarks.shape)
        est = umeyama(kitti_landmarks, dst)
        ref = gtsam.Similarity3.Align([(d, s) for d, s in zip(dst, kitti_landmarks)])
        np.testing.assert_allclose(est.R, ref.rotation().matrix(), atol=1e-9)
        assert est.s == pytest.approx(ref.scale(), rel=1e-9)
        np.testing.assert_allclose(est.t, ref.scale() * ref.translation(), atol=1e-6)

    def test_is_the_least_squares_optimum(self, known_sim3, kitti_landmarks):
        """Brute force: no perturbation of rotation, scale or translation on a grid lowers the squared error."""
        src = kitti_landmarks[::4]
        dst = known_sim3.apply(src) + np.random.default_rng(1).normal(0, 0.5, src.shape)
        est = umeyama(src, dst)
        best = cost(est, src, dst)
        steps = (-1e-3, 0.0, 1e-3)
        for w in itertools.product(steps, repeat=3):
            for ds, dt in itertools.product((0.999, 1.0, 1.001), ((0, 0, 0), (0.01, 0, 0), (0, 0, -0.01))):
                moved = Sim3(est.s * ds, rot(w) @ est.R, est.t + dt)
                assert cost(moved, src, dst) >= best - 1e-9

    def test_mirror_image_gives_the_best_rotation_not_a_reflection(self, kitti_landmarks):
        """Break-it check for the reflection fix: without it R would have det -1 (Sim3 refuses that) and the
        squared error would not be the optimum among rotations."""
        import gtsam

        src = kitti_landmarks[::3]
        dst = src * np.array([-1.0, 1.0, 1.0])
        est = umeyama(src, dst)
        assert np.linalg.det(est.R) == pytest.approx(1.0)
        ref = gtsam.Similarity3.Align([(d, s) for d, s in zip(dst, src)])
        ref_sim3 = Sim3(ref.scale(), ref.rotation().matrix(), ref.scale() * ref.translation())
        assert cost(est, src, dst) <= cost(ref_sim3, src, dst) + 1e-6
        for w in itertools.product((-1e-3, 0.0, 1e-3), repeat=3):
            assert cost(Sim3(est.s, rot(w) @ est.R, est.t), src, dst) >= cost(est, src, dst) - 1e-9

    def test_scale_is_estimated_or_fixed(self, known_sim3, kitti_landmarks):
        dst = known_sim3.apply(kitti_landmarks)
        assert umeyama(kitti_landmarks, dst).s == pytest.approx(2.5, rel=1e-9)
        rigid = umeyama(kitti_landmarks, dst, with_scale=False)
        assert rigid.s == 1.0 and rigid.errors(known_sim3)[2] > 1.0
        unit = Sim3(1.0, known_sim3.R, known_sim3.t)
        assert umeyama(kitti_landmarks, unit.apply(kitti_landmarks), with_scale=False).errors(unit)[2] < 1e-9

    def test_zero_weights_drop_points(self, known_sim3, kitti_landmarks, with_outliers):
        dst, bad = with_outliers(known_sim3.apply(kitti_landmarks), 0.3, np.random.default_rng(2))
        weighted = umeyama(kitti_landmarks, dst, weights=(~bad).astype(float))
        assert weighted.errors(known_sim3)[0] < 1e-4
        assert umeyama(kitti_landmarks, dst).errors(known_sim3)[0] > 0.1  # the outliers matter without weights

    @pytest.mark.parametrize("src, dst, weights", [
        (np.zeros((2, 3)), np.zeros((2, 3)), None),  # too few points
        (np.outer(np.arange(10.0), [1.0, 2.0, 0.5]), np.outer(np.arange(10.0), [2.0, 1.0, 0.0]), None),  # collinear
        (np.ones((5, 3)), np.ones((5, 3)), None),  # coincident
        (np.full((5, 3), np.nan), np.zeros((5, 3)), None),  # NaN
        (np.zeros((5, 3)), np.zeros((4, 3)), None),  # different counts
        (np.zeros((5, 2)), np.zeros((5, 2)), None),  # not 3D
        (np.eye(3), np.eye(3), np.array([1.0, 1.0, -1.0])),  # negative weight
        (np.eye(3), np.eye(3), np.array([1.0, 1.0, 0.0])),  # two weighted points
    ], ids=["two", "collinear", "coincident", "nan", "counts", "2d", "negative-weight", "zero-weights"])
    def test_degenerate_input_raises_one_line(self, src, dst, weights):
        with pytest.raises(ConfigError) as err:
            umeyama(src, dst, weights=weights)
        assert "\n" not in str(err.value)


class TestRansacSim3:
    @pytest.mark.parametrize("fraction", [0.3, 0.5])
    def test_recovers_the_transform_among_outliers(self, known_sim3, kitti_landmarks, with_outliers, fraction):
        rng = np.random.default_rng(3)
        clean = known_sim3.apply(kitti_landmarks + rng.normal(0, 0.05, kitti_landmarks.shape))
        dst, bad = with_outliers(clean, fraction, rng)
        est, mask = ransac_sim3(kitti_landmarks, dst)
        angle, scale, trans = est.errors(known_sim3)
        assert angle < 0.5 and scale < 0.01 and trans < 0.5
        assert (mask & ~bad).sum() >= 0.95 * (~bad).sum() and (mask & bad).sum() <= 0.02 * bad.sum()

    def test_a_local_patch_as_an_overlap_gives_it(self, known_sim3, kitti_poses, landmarks, with_outliers):
        """What a map merge sees: points of 4 neighbouring keyframes (about 3 m of road), 40% wrong matches."""
        rng = np.random.default_rng(4)
        src = landmarks(kitti_poses("00")[100:104])
        dst, bad = with_outliers(known_sim3.apply(src + rng.normal(0, 0.03, src.shape)), 0.4, rng)
        est, mask = ransac_sim3(src, dst)
        angle, scale, _ = est.errors(known_sim3)
        assert angle < 0.5 and scale < 0.01 and not (mask & bad).any()

    def test_refinement_beats_the_minimal_sample(self, known_sim3, kitti_landmarks, with_outliers):
        rng = np.random.default_rng(5)
        dst, _ = with_outliers(known_sim3.apply(kitti_landmarks + rng.normal(0, 0.2, kitti_landmarks.shape)), 0.3,
                               rng)
        raw = ransac_sim3(kitti_landmarks, dst, {"refine_iterations": 0})[0].errors(known_sim3)
        refined = ransac_sim3(kitti_landmarks, dst)[0].errors(known_sim3)
        assert refined[0] < raw[0] and refined[1] < raw[1]

    def test_finds_the_brute_force_consensus(self, known_sim3, kitti_landmarks, with_outliers):
        """Every one of the C(15, 3) minimal samples scored: RANSAC's inliers are the largest consensus set."""
        rng = np.random.default_rng(6)
        src = kitti_landmarks[::40]
        dst, bad = with_outliers(known_sim3.apply(src), 0.4, rng)
        solver = Sim3Ransac({"min_inliers": 3})
        thr = solver.threshold_for(dst)
        best = 0
        for tri in itertools.combinations(range(len(src)), 3):
            try:
                T = umeyama(src[list(tri)], dst[list(tri)])
            except ConfigError:
                continue
            best = max(best, int((np.linalg.norm(T.apply(src) - dst, axis=1) < thr).sum()))
        _, mask = solver(src, dst)
        assert mask.sum() == best == (~bad).sum()
        np.testing.assert_array_equal(mask, ~bad)

    def test_same_seed_same_result(self, known_sim3, kitti_landmarks, with_outliers):
        dst, _ = with_outliers(known_sim3.apply(kitti_landmarks), 0.5, np.random.default_rng(7))
        dst = dst + np.random.default_rng(8).normal(0, 0.1, dst.shape)
        a, b = ransac_sim3(kitti_landmarks, dst, {"seed": 3}), ransac_sim3(kitti_landmarks, dst, {"seed": 3})
        np.testing.assert_array_equal(a[0].matrix(), b[0].matrix())
        np.testing.assert_array_equal(a[1], b[1])

    def test_relative_threshold_is_free_of_units(self, known_sim3, kitti_landmarks, with_outliers):
        rng = np.random.default_rng(9)
        dst, _ = with_outliers(known_sim3.apply(kitti_landmarks + rng.normal(0, 0.05, kitti_landmarks.shape)), 0.3,
                               rng)
        metres, km = ransac_sim3(kitti_landmarks, dst), ransac_sim3(kitti_landmarks, dst / 1000.0)
        np.testing.assert_array_equal(metres[1], km[1])
        assert km[0].s == pytest.approx(metres[0].s / 1000.0, rel=1e-6)

    def test_absolute_threshold_is_in_dst_units(self, known_sim3, kitti_landmarks):
        dst = known_sim3.apply(kitti_landmarks + np.random.default_rng(10).normal(0, 0.05, kitti_landmarks.shape))
        assert ransac_sim3(kitti_landmarks, dst, {"threshold_mode": "absolute", "threshold": 1e-4}) is None
        est, mask = ransac_sim3(kitti_landmarks, dst, {"threshold_mode": "absolute", "threshold": 1.0})
        assert mask.mean() > 0.95 and est.errors(known_sim3)[0] < 0.5

    def test_no_transform_gives_none(self, kitti_landmarks):
        rng = np.random.default_rng(11)
        assert ransac_sim3(kitti_landmarks[:5], kitti_landmarks[:5]) is None  # fewer than min_inliers
        line = np.outer(np.arange(20.0), [1.0, 0.0, 2.0])
        assert ransac_sim3(line, 3 * line) is None  # collinear: only degenerate samples
        assert ransac_sim3(kitti_landmarks, rng.permutation(kitti_landmarks)) is None  # matches all wrong
        assert ransac_sim3(np.zeros((0, 3)), np.zeros((0, 3))) is None

    def test_points_whose_products_overflow_are_degenerate_samples(self, kitti_landmarks):
        """Finite points whose products overflow made an infinite cross-covariance, on which LAPACK's SVD never
        returned (one far point: a robot with fx = 1e-300 and a depth map hung the server, holding the recognizer's
        lock, for good) or raised (all far: a 500)."""
        import threading

        one_far, all_far = kitti_landmarks.copy(), kitti_landmarks * 1e160
        one_far[0, 0] = 1e200
        out: list = []
        worker = threading.Thread(target=lambda: out.append((ransac_sim3(one_far, 3 * one_far),
                                                             ransac_sim3(all_far, 3 * all_far))), daemon=True)
        worker.start()
        worker.join(timeout=20)
        assert not worker.is_alive(), "RANSAC hung on points whose products overflow"
        assert len(out) == 1, "RANSAC raised on points whose products overflow"
        (found, inliers), none = out[0]
        assert found.s == pytest.approx(3.0) and inliers[1:].all() and none is None
        with pytest.raises(ConfigError, match="too far apart"):
            umeyama(all_far, 2 * all_far)

    def test_malformed_input_raises(self, kitti_landmarks):
        bad = kitti_landmarks.copy()
        bad[3, 1] = np.inf
        with pytest.raises(ConfigError, match="finite"):
            ransac_sim3(kitti_landmarks, bad)
        with pytest.raises(ConfigError, match="same n"):
            ransac_sim3(kitti_landmarks, kitti_landmarks[:-1])

    @pytest.mark.parametrize("conf, key", [({"threshold": 0}, "sim3.threshold"), ({"loss": "l1"}, "sim3.loss"),
                                           ({"min_inliers": 2}, "sim3.min_inliers"), ({"seed": -1}, "sim3.seed"),
                                           ({"iters": 5}, "sim3.iters")])
    def test_bad_conf_is_refused(self, conf, key, kitti_landmarks):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            ransac_sim3(kitti_landmarks, kitti_landmarks, conf)

    def test_every_conf_key_has_a_rule(self):
        assert set(Sim3Ransac.default_conf) == set(Sim3Ransac.conf_rules)
