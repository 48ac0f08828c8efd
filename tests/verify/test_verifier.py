import random
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from verify.features import Features
from verify.geometry import GeometryResult
from verify.verifier import (NOT_CHECKED, MATCHERS, RatioTestMatcher, Verification, _checked_in_turn, create_verifier,
                             scale_change)


class TestRatioTestMatcher:
    def test_true_vs_far_candidates(self, sift_features, sample_K):
        v = RatioTestMatcher()
        out = v.verify(sift_features(55), [sift_features(5), sift_features(30)], sample_K)
        assert len(out) == 2 and all(isinstance(o, Verification) for o in out)
        true, far = out
        assert true.matches == len(true.pairs) > 150
        assert true.inliers > 150 and far.inliers < 30
        assert true.geometry.model == "essential"
        assert true.pairs.shape == (true.matches, 2) and true.pairs.dtype == np.int64

    def test_min_matches_skips_geometry(self, sift_features, sample_K):
        v = RatioTestMatcher()
        far = v.verify(sift_features(55), [sift_features(30)], sample_K, min_matches=1000)[0]
        assert far.geometry.model == "not checked" and far.inliers == NOT_CHECKED and far.matches > 0

    def test_no_candidates_and_empty_features(self, sift_features, sample_K):
        v = RatioTestMatcher()
        assert v.verify(sift_features(55), [], sample_K) == []
        out = v.verify(Features.empty(), [sift_features(5)], sample_K)
        assert out[0].matches == 0 and out[0].inliers == NOT_CHECKED and out[0].pairs.shape == (0, 2)
        out = v.verify(sift_features(55), [Features.empty()], sample_K)
        assert out[0].matches == 0 and out[0].inliers == NOT_CHECKED

    def test_branch_and_bound_keeps_the_best(self, sift_features, sample_K):
        """Skipping candidates that cannot win changes no winner: same best as checking all."""
        v = RatioTestMatcher()
        cands = [sift_features(i) for i in (30, 5, 6, 4, 40)]
        full = v.verify(sift_features(55), cands, sample_K, min_inliers=50, check_all=True)
        fast = v.verify(sift_features(55), cands, sample_K, min_inliers=50, check_all=False)
        assert [f.matches for f in full] == [f.matches for f in fast]
        best = max(range(len(cands)), key=lambda i: (full[i].inliers, full[i].matches))
        assert max(range(len(cands)), key=lambda i: (fast[i].inliers, fast[i].matches)) == best
        assert fast[best].inliers == full[best].inliers > 50
        skipped = [f for f in fast if f.inliers == NOT_CHECKED]
        assert skipped and all(f.matches < fast[best].inliers for f in skipped)

    def test_mutual_option(self, sift_features):
        plain = RatioTestMatcher().match_many(sift_features(55), [sift_features(5)])[0]
        mutual = RatioTestMatcher({"mutual": True}).match_many(sift_features(55), [sift_features(5)])[0]
        assert set(map(tuple, mutual.tolist())) <= set(map(tuple, plain.tolist()))
        assert 0 < len(mutual) < len(plain)


class CountingPool(ThreadPoolExecutor):
    """A one-thread executor that counts the jobs it was given."""

    def __init__(self):
        super().__init__(1)
        self.jobs = 0

    def submit(self, *args, **kwargs):
        self.jobs += 1
        return super().submit(*args, **kwargs)


class TestVerifyWorker:
    """A second thread (``pool``) matches and checks beside the caller: the same result as one thread."""

    @pytest.mark.parametrize("check_all", [False, True])
    def test_same_as_one_thread(self, sift_features, sample_K, check_all):
        v = RatioTestMatcher()
        cands = [sift_features(i) for i in (30, 5, 6, 4, 40, 7)]
        alone = v.verify(sift_features(55), cands, sample_K, 5, 50, check_all)
        with CountingPool() as pool:
            for _ in range(3):
                both = v.verify(sift_features(55), cands, sample_K, 5, 50, check_all, pool)
                for a, b in zip(alone, both):
                    assert (a.matches, a.inliers, a.geometry.model) == (b.matches, b.inliers, b.geometry.model)
                    np.testing.assert_array_equal(a.pairs, b.pairs)
                    np.testing.assert_array_equal(a.geometry.mask, b.geometry.mask)
            assert pool.jobs == 6  # each call: half the matching, then a lane of checks
        checked = sum(a.inliers != NOT_CHECKED for a in alone)
        # all: 4 pairs over 50 matches checked; bound: one (266 inliers), the others' checks made ahead are dropped
        assert checked == 4 if check_all else checked == 1 and sum(a.matches > 50 for a in alone) == 4

    def test_every_sequential_check_is_made(self):
        """Checks taken in turn by two threads, finishing in any order: every check the sequential branch and bound
        makes is among them (a skipped candidate could not win), whatever the timing."""
        rng = random.Random(3)
        with ThreadPoolExecutor(1) as pool:
            for _ in range(40):
                matches = sorted((rng.randint(10, 300) for _ in range(rng.randint(1, 8))), reverse=True)
                inliers = [rng.randint(0, m) for m in matches]
                ran = []

                def check(i):
                    time.sleep(rng.random() * 1e-3)
                    ran.append(threading.get_ident())
                    return GeometryResult(inliers[i], np.zeros(0, bool), "essential")

                done = _checked_in_turn(list(range(len(matches))), matches, check, False, pool)
                best, sequential = -1, []
                for i, m in enumerate(matches):
                    if best > m:
                        continue
                    sequential.append(i)
                    best = max(best, inliers[i])
                assert set(sequential) <= set(done) and all(done[i].inliers == inliers[i] for i in done)
                assert len(_checked_in_turn(list(range(len(matches))), matches, check, True, pool)) == len(matches)


class TestCreateVerifier:
    def test_by_name_and_errors(self):
        v = create_verifier({"name": "ratio", "ratio": 0.7}, {"model": "fundamental"})
        assert isinstance(v, RatioTestMatcher)
        assert v.conf["ratio"] == 0.7 and v.geometry.conf["model"] == "fundamental"
        assert "ratio" in MATCHERS.names()
        with pytest.raises(ConfigError, match="unknown matcher 'lightglue'"):
            create_verifier({"name": "lightglue"})
        with pytest.raises(ConfigError, match="matcher.ratios"):
            create_verifier({"ratios": 0.7})


class TestMetricIsAPropertyOfTheFeatures:
    """The matcher uses ``Features.metric``, never a guess from the dtype: SIFT stored as uint8 is still L2."""

    def test_compact_sift_matches_like_float_sift(self, sift_features):
        q, c = sift_features(55), sift_features(5)
        assert q.compact().descriptors.dtype == np.uint8 and q.compact().metric == "l2"
        v = RatioTestMatcher()
        plain = v.match_many(q, [c])[0]
        compact = v.match_many(q.compact(), [c.compact()])[0]
        assert len(plain) > 50
        np.testing.assert_array_equal(compact, plain)

    def test_binary_features_use_hamming(self):
        rng = np.random.default_rng(0)
        desc = rng.integers(0, 256, (40, 32), dtype=np.uint8)
        kp = rng.uniform(0, 100, (40, 2)).astype(np.float32)
        noisy = desc.copy()
        noisy[:, 0] ^= 1  # one bit flipped: the Hamming nearest neighbour is still the same feature
        a = Features(kp, desc, np.ones(40, np.float32), "hamming")
        b = Features(kp, noisy, np.ones(40, np.float32), "hamming")
        pairs = RatioTestMatcher().match_many(a, [b])[0]
        assert len(pairs) == 40 and (pairs[:, 0] == pairs[:, 1]).all()

    def test_mixed_metrics_refused(self, sift_features):
        binary = Features(np.zeros((3, 2), np.float32), np.zeros((3, 32), np.uint8), np.ones(3, np.float32), "hamming")
        with pytest.raises(ConfigError, match="cannot match l2 descriptors against hamming"):
            RatioTestMatcher().match_many(sift_features(55), [binary])

    def test_metric_survives_the_database(self, tmp_path, sift_features):
        from retrieval.database import KeyframeDatabase, KeyframeRecord

        with KeyframeDatabase(tmp_path / "kf.h5", {}) as db:
            db.append(KeyframeRecord(0, np.zeros(8, np.float32), sift_features(5)))
            back = db.features(0)
        assert back.metric == "l2" and back.descriptors.dtype == np.float32


class TestScaleChange:
    """``scale_change``: the median of ``log2(query scale / candidate scale)`` over the geometric inliers. The bundled
    sample's second pass (50-99) drives the first pass's road again; frame 57 stands at 7, 2.9 m past 6."""

    def test_sign_says_which_frame_is_nearer_the_scene(self, sift_features, sample_K):
        v, q = RatioTestMatcher(), sift_features(57)
        behind, at, ahead = (scale_change(q, sift_features(r), v.verify(q, [sift_features(r)], sample_K)[0])
                             for r in (5, 7, 9))
        assert behind > 0.2 and ahead < -0.2  # measured: +0.39, -0.38
        assert abs(at) < 0.15 and abs(at) < min(behind, -ahead)  # measured: +0.08

    def test_is_the_median_over_the_inliers(self, sift_features, sample_K):
        q, c = sift_features(57), sift_features(6)
        check = RatioTestMatcher().verify(q, [c], sample_K)[0]
        pairs = check.pairs[check.geometry.mask]
        brute = np.median([np.log2(q.scales[i] / c.scales[j]) for i, j in pairs.tolist()])
        assert check.inliers > 50 and scale_change(q, c, check) == pytest.approx(brute, abs=1e-9)

    def test_too_few_inliers_or_none_checked_give_nan(self, sift_features, sample_K):
        v, q = RatioTestMatcher(), sift_features(57)
        unchecked = v.verify(q, [sift_features(30)], sample_K, min_matches=10_000)[0]
        assert unchecked.inliers == NOT_CHECKED and np.isnan(scale_change(q, sift_features(30), unchecked))
        empty = v.verify(q, [Features.empty()], sample_K)[0]
        assert np.isnan(scale_change(q, Features.empty(), empty))
