"""retrieval.mild: multi-index hashing similarity against the brute-force eq. 3 / eq. 1, and P_recall."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cae_lcd.core.errors import ConfigError
from retrieval.mild import (MildDescriptor, MultiIndexHash, brute_force_similarity, bucket_cap, expected_recall,
                            hamming_distances, recall_probability)
from verify.features import ORB


@pytest.fixture(scope="module")
def orb_descriptors(sample_image):
    """ORB descriptors of four real sample frames (two of them a revisit: 5 and 55), 120 per frame."""
    orb = ORB({"max_features": 120})
    return [orb.extract(sample_image(i)).descriptors for i in (5, 6, 30, 55)]


def flip_bits(desc: np.ndarray, n_bits: int, rng: np.random.Generator) -> np.ndarray:
    bits = np.unpackbits(desc, axis=1)
    for row in bits:
        row[rng.choice(256, n_bits, replace=False)] ^= 1
    return np.packbits(bits, axis=1)


class TestMultiIndexHash:
    def test_equals_brute_force_eq3(self, orb_descriptors):
        *stored, query = orb_descriptors
        index = MultiIndexHash(m=16)
        for d in stored:
            index.add(d)
        np.testing.assert_allclose(index.query(query), brute_force_similarity(query, stored, 16), rtol=1e-12)

    @pytest.mark.parametrize("m", [8, 32])  # 32-bit keys: binary search; 8-bit keys: direct addressing
    def test_equals_brute_force_other_m(self, orb_descriptors, m):
        *stored, query = orb_descriptors
        index = MultiIndexHash(m=m)
        for d in stored:
            index.add(d)
        np.testing.assert_allclose(index.query(query), brute_force_similarity(query, stored, m), rtol=1e-12)

    def test_equals_brute_force_with_over_full_entries_skipped(self, orb_descriptors):
        *stored, query = orb_descriptors
        rng = np.random.default_rng(1)
        base = query[:20]

        def randomised(desc, keep):  # 16-bit substrings outside ``keep`` replaced by random bits
            words = desc.view(">u2").copy()
            others = [t for t in range(16) if t not in keep]
            words[:, others] = rng.integers(0, 1 << 16, (len(desc), len(others)))
            return words.view(np.uint8)

        # A is the query with one bit flipped in each of substrings 1-4: it shares substring 0 and 5-15 with it. Five
        # descriptors per query feature that share only substring 0 crowd its entries past the cap, so A's pairs
        # count through table 5 (the first table where they match in an entry that is not skipped)
        near = base.view(">u2").copy()
        near[:, 1:5] ^= 1
        stored = [*stored, near.view(np.uint8), *[randomised(base, (0,)) for _ in range(5)]]
        index = MultiIndexHash(m=16, max_bucket=2.0)
        for i, d in enumerate(stored):
            index.add(d)
            if i == 1:
                index.query(query)  # the first images go to the sorted tables, the rest to the tail
        got = index.query(query)
        np.testing.assert_allclose(got, brute_force_similarity(query, stored, 16, max_bucket=2.0), rtol=1e-12)
        assert got[3] > 0

    def test_equals_eq1_for_pairs_that_must_share_a_key(self, orb_descriptors):
        # with d0 < m every pair that phi counts is under m bits apart, so it shares a substring: eq. 3 == eq. 1
        rng = np.random.default_rng(0)
        base = orb_descriptors[0]
        near = flip_bits(base, 10, rng)
        index = MultiIndexHash(m=16, d0=15)
        index.add(base)
        eq1 = brute_force_similarity(near, [base], 16, d0=15, shared_key_only=False)
        assert eq1[0] > 0
        np.testing.assert_allclose(index.query(near), eq1, rtol=1e-12)

    def test_revisit_scores_highest(self, orb_descriptors):
        index = MultiIndexHash()
        for d in orb_descriptors[:3]:
            index.add(d)
        sims = index.query(orb_descriptors[3])  # frame 55 revisits frame 5 (and 6 next to it)
        assert sims[0] > sims[2] and sims[1] > sims[2]

    def test_over_full_buckets_skipped(self, orb_descriptors):
        d = orb_descriptors[0]
        same = np.repeat(d[:1], 50, axis=0)  # 50 identical descriptors: every key of theirs holds 50 features
        index = MultiIndexHash(max_bucket=10)
        index.add(same)
        assert index.query(d[:1])[0] == 0.0
        assert MultiIndexHash().query(d[:1]).shape == (0,)

    def test_empty_and_bad_input(self, orb_descriptors):
        index = MultiIndexHash()
        index.add(np.zeros((0, 32), np.uint8))
        assert index.query(orb_descriptors[0]).tolist() == [0.0]
        assert index.compared_pairs(np.zeros((0, 32), np.uint8)).shape == (0, 2)
        with pytest.raises(ConfigError, match="uint8"):
            index.add(np.zeros((3, 128), np.float32))
        with pytest.raises(ConfigError, match="divide 256"):
            MultiIndexHash(m=7)


class TestBucketCap:
    def test_relative_to_the_mean_entry(self):
        assert bucket_cap(0, 10**6, 16) == float("inf")
        assert bucket_cap(4.0, 1000, 16) == 4.0  # fewer features than keys: at least 1 a key
        assert bucket_cap(4.0, 2 * 65536, 16) == 8.0


class TestMildDescriptor:
    def test_orb_descriptors_and_small_frames_enlarged(self, sample_image):
        frame = sample_image(5)
        desc = MildDescriptor()(frame)
        assert desc.dtype == np.uint8 and desc.shape[1] == 32 and 700 <= len(desc) <= 800
        tiny = cv2.resize(frame, (64, 32), interpolation=cv2.INTER_AREA)
        assert len(MildDescriptor()(tiny)) > 50  # enlarged to 256 first
        assert MildDescriptor({"min_size": None})(tiny).shape == (0, 32)  # ORB's border leaves nothing at 64x32

    def test_conf_checked(self):
        with pytest.raises(ConfigError, match="divide 256"):
            MildDescriptor({"m": 7})
        with pytest.raises(ConfigError, match="max_bucket"):
            MildDescriptor({"max_bucket": -1})


class TestHammingDistances:
    def test_known(self):
        a = np.zeros((2, 32), np.uint8)
        b = a.copy()
        b[0, 0], b[1, 31] = 0b1011, 0xFF
        assert hamming_distances(a, b).tolist() == [3, 8]


class TestRecallProbability:
    @pytest.mark.parametrize("m,d", [(16, 20), (16, 32), (16, 48), (8, 30), (32, 64)])
    def test_matches_monte_carlo(self, m, d):
        # the model behind eq. 8: each of the d differing bits falls in a substring chosen uniformly
        rng = np.random.default_rng(1)
        trials = 20000
        hit_all = sum(len(np.unique(rng.integers(0, m, d))) == m for _ in range(trials))
        assert recall_probability(m, d) == pytest.approx(1 - hit_all / trials, abs=0.01)

    def test_edges(self):
        assert recall_probability(16, 15) == 1.0  # fewer differing bits than substrings: one is always clean
        assert recall_probability(16, 256) == pytest.approx(16 * (15 / 16) ** 256, rel=0.01)  # one clean substring

    def test_r_and_e_choose_m(self):
        # more tables (shorter substrings) retrieve more inliers and cost more outlier comparisons
        r = [expected_recall(m, 32, 10) for m in (8, 16, 32)]
        e = [expected_recall(m, 128, 20) for m in (8, 16, 32)]
        assert r == sorted(r) and e == sorted(e)
        assert r[1] > 0.8 and e[1] < 0.02  # MILD's m = 16: most inliers, few outliers compared
