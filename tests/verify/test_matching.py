"""The per-frame fast path (match_ratio_many) against the brute-force reference (match_ratio) and OpenCV."""

import cv2
import numpy as np
import pytest

from verify.matching import (EMPTY_MATCHES, match_ratio, match_ratio_many, pairwise_hamming, pairwise_sq_l2)


def as_set(m: np.ndarray) -> set:
    return set(map(tuple, np.asarray(m).tolist()))


def cv2_ratio(xq, xb, ratio=0.8, norm=cv2.NORM_L2):
    """Independent reference: OpenCV brute-force 2-NN with Lowe's ratio test."""
    knn = cv2.BFMatcher(norm).knnMatch(np.ascontiguousarray(xq), np.ascontiguousarray(xb), k=2)
    return {(m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance}


def cv2_mutual(xq, xb, norm=cv2.NORM_L2):
    return {(m.queryIdx, m.trainIdx) for m in cv2.BFMatcher(norm, crossCheck=True).match(xq, xb)}


@pytest.fixture(scope="module")
def descs(sift_features):
    """Real SIFT descriptors: query frame 55, candidates 5 (true revisit), 30 (far), 54 (neighbour)."""
    return {i: sift_features(i).descriptors for i in (55, 5, 30, 54)}


class TestMatchRatio:
    @pytest.mark.parametrize("cand", [5, 30, 54])
    def test_equals_opencv(self, descs, cand):
        m = match_ratio(descs[55], descs[cand])
        assert m.dtype == np.int64 and m.shape[1] == 2
        assert as_set(m) == cv2_ratio(descs[55], descs[cand])
        assert len(np.unique(m[:, 0])) == len(m)  # one match per query feature

    @pytest.mark.parametrize("ratio", [0.6, 0.9])
    def test_ratio_values(self, descs, ratio):
        assert as_set(match_ratio(descs[55], descs[5], ratio)) == cv2_ratio(descs[55], descs[5], ratio)

    def test_mutual(self, descs):
        m = match_ratio(descs[55], descs[5], mutual=True)
        assert as_set(m) == cv2_ratio(descs[55], descs[5]) & cv2_mutual(descs[55], descs[5])
        assert len(m) < len(match_ratio(descs[55], descs[5]))

    def test_true_pair_has_more_matches(self, descs):
        # measured with the default SIFT (500 features): ~270 ratio-test matches for the revisit, ~17 for the far pair
        assert len(match_ratio(descs[55], descs[5])) > 150
        assert len(match_ratio(descs[55], descs[30])) < 60

    def test_hamming_equals_opencv(self):
        rng = np.random.default_rng(0)
        xq = rng.integers(0, 256, (300, 32), dtype=np.uint8)
        xb = rng.integers(0, 256, (400, 32), dtype=np.uint8)
        xb[:100] = xq[:100] ^ (rng.random((100, 32)) < 0.02).astype(np.uint8)  # near-duplicates: real matches
        m = match_ratio(xq, xb, metric="hamming")
        assert as_set(m) == cv2_ratio(xq, xb, norm=cv2.NORM_HAMMING)
        assert len(m) >= 90

    def test_empty_inputs(self, descs):
        for xq, xb in [(descs[55][:0], descs[5]), (descs[55], descs[5][:0]), (descs[55][:0], descs[5][:0])]:
            m = match_ratio(xq, xb)
            assert m.shape == (0, 2) and m.dtype == np.int64

    def test_single_candidate_feature(self, descs):
        # no second neighbour: the ratio test cannot reject, every query feature matches the only candidate
        m = match_ratio(descs[55][:7], descs[5][:1])
        np.testing.assert_array_equal(m, np.stack([np.arange(7), np.zeros(7, int)], axis=1))


class TestMatchRatioMany:
    def test_equals_match_ratio_and_opencv(self, descs):
        cands = [descs[5], descs[30], descs[54]]
        many = match_ratio_many(descs[55], cands)
        assert len(many) == 3
        for xb, m in zip(cands, many):
            assert m.dtype == np.int64 and m.shape[1] == 2
            assert as_set(m) == as_set(match_ratio(descs[55], xb)) == cv2_ratio(descs[55], xb)

    def test_uint8_candidates(self, descs):
        # the detector keeps keyframe SIFT descriptors as uint8 (lossless); results must not change
        cands = [descs[5].astype(np.uint8), descs[30].astype(np.uint8)]
        for m, xb in zip(match_ratio_many(descs[55], cands), (descs[5], descs[30])):
            assert as_set(m) == as_set(match_ratio(descs[55], xb))

    def test_mutual(self, descs):
        m = match_ratio_many(descs[55], [descs[5], descs[30]], mutual=True)
        assert as_set(m[0]) == as_set(match_ratio(descs[55], descs[5], mutual=True))
        assert as_set(m[1]) == as_set(match_ratio(descs[55], descs[30], mutual=True))

    def test_random_float_vectors(self):
        rng = np.random.default_rng(1)
        xq = rng.normal(size=(200, 64)).astype(np.float32)
        xbs = [rng.normal(size=(n, 64)).astype(np.float32) for n in (1, 2, 150, 500)]
        xbs[2][:50] = xq[:50] + 0.05 * rng.normal(size=(50, 64)).astype(np.float32)
        for m, xb in zip(match_ratio_many(xq, xbs, 0.8), xbs):
            assert as_set(m) == as_set(match_ratio(xq, xb, 0.8))
        assert len(match_ratio_many(xq, xbs)[2]) >= 45

    def test_hamming(self):
        rng = np.random.default_rng(2)
        xq = rng.integers(0, 256, (100, 32), dtype=np.uint8)
        xbs = [rng.integers(0, 256, (n, 32), dtype=np.uint8) for n in (50, 120)]
        for m, xb in zip(match_ratio_many(xq, xbs, metric="hamming"), xbs):
            assert as_set(m) == as_set(match_ratio(xq, xb, metric="hamming"))

    def test_empty_inputs(self, descs):
        assert match_ratio_many(descs[55], []) == []
        out = match_ratio_many(descs[55], [descs[5][:0], descs[5], descs[30][:0]])
        assert [m.shape for m in out][0] == (0, 2) and out[2].shape == (0, 2)
        assert as_set(out[1]) == as_set(match_ratio(descs[55], descs[5]))
        for m in match_ratio_many(descs[55][:0], [descs[5], descs[30]]):
            assert m.shape == (0, 2) and m.dtype == np.int64
        for m in match_ratio_many(descs[55], [descs[5][:0], descs[5][:0]]):
            assert m.shape == (0, 2)
        assert EMPTY_MATCHES.shape == (0, 2)


class TestPairwiseSqL2:
    def test_against_numpy(self, descs):
        a, b = descs[55][:50], descs[5][:70]
        ref = ((a[:, None, :].astype(np.float64) - b[None, :, :]) ** 2).sum(-1)
        np.testing.assert_allclose(pairwise_sq_l2(a, b), ref, rtol=1e-6)
        assert pairwise_sq_l2(a, a).diagonal().max() == 0.0


class TestPairwiseHamming:
    def test_against_bit_count(self):
        rng = np.random.default_rng(3)
        a = rng.integers(0, 256, (20, 32), dtype=np.uint8)
        b = rng.integers(0, 256, (30, 32), dtype=np.uint8)
        ref = np.unpackbits(a[:, None, :] ^ b[None, :, :], axis=2).sum(-1)
        np.testing.assert_array_equal(pairwise_hamming(a, b), ref)


@pytest.mark.skipif(not hasattr(__import__("torch"), "_int_mm"), reason="this torch has no 8-bit product")
class TestByteProducts:
    """SIFT's descriptors (integers 0-255) are matched from exact 8-bit products where those are faster: the same
    distances as the float32 GEMM bit for bit, hence the same matches; anything else takes the float32 GEMM."""

    def test_byte_distances_are_the_float_distances_bit_for_bit(self, descs):
        from verify.matching import _ByteDistances

        extremes = np.array([[0] * 128, [255] * 128, [0, 255] * 64], np.uint8)
        for xq, xb in [(descs[55], descs[5]), (descs[5], descs[30]), (extremes, extremes), (extremes, descs[54])]:
            fast = _ByteDistances(xq.astype(np.uint8)).exact_to(_ByteDistances(xb.astype(np.uint8)))
            assert fast.dtype == np.int32
            np.testing.assert_array_equal(fast.astype(np.float32), pairwise_sq_l2(xq, xb))

    @pytest.mark.parametrize("faster", [True, False], ids=["bytes", "float32"])
    def test_either_product_gives_the_brute_force_matches(self, descs, monkeypatch, faster):
        import verify.matching as matching

        monkeypatch.setattr(matching, "_BYTES_FASTER", faster)
        used = []
        monkeypatch.setattr(matching._ByteDistances, "exact_to", lambda self, other,
                            to=matching._ByteDistances.exact_to: used.append(1) or to(self, other))
        # the last two hold the same features twice (ties: the first nearest neighbour among equals, as numpy's)
        cands = [descs[5], descs[30].astype(np.uint8), descs[54][:0], descs[54], np.vstack([descs[5], descs[5][:40]]),
                 np.vstack([descs[30][:40], descs[30]])]
        for query in (descs[55], np.vstack([descs[55], descs[55][:40]])):  # ties on the query's side too
            for mutual in (False, True):
                for m, xb in zip(match_ratio_many(query, cands, mutual=mutual), cands):
                    np.testing.assert_array_equal(m, match_ratio(query, xb, mutual=mutual))
        assert len(used) == (4 * sum(len(xb) > 0 for xb in cands) if faster else 0)  # one product a candidate

    def test_descriptors_that_are_not_bytes_take_the_float_product(self, descs, monkeypatch):
        import verify.matching as matching

        monkeypatch.setattr(matching, "_BYTES_FASTER", True)
        monkeypatch.setattr(matching._ByteDistances, "exact_to", lambda *_: pytest.fail("not bytes: no 8-bit product"))
        for cands in ([descs[5] + 0.5], [descs[5] * 2.0], [descs[5] - 1.0]):  # a fraction, over 255, under 0
            m = match_ratio_many(descs[55], cands)[0]
            np.testing.assert_array_equal(m, match_ratio(descs[55], cands[0]))


@pytest.mark.skipif(not hasattr(__import__("torch"), "_int_mm"), reason="this torch has no 8-bit product")
class TestByteForms:
    """A verifier keeps the 8-bit forms of the descriptors it matched lately: the same matches, each form made once."""

    def test_the_same_matches_each_form_made_once(self, descs, monkeypatch):
        import verify.matching as matching

        monkeypatch.setattr(matching, "_BYTES_FASTER", True)
        made = []
        monkeypatch.setattr(matching, "_form", lambda x, form=matching._form: made.append(id(x)) or form(x))
        forms = matching.ByteForms(keep=3)
        query, cands = descs[55], [descs[5].astype(np.uint8), descs[30].astype(np.uint8)]
        for _ in range(2):
            for m, xb in zip(match_ratio_many(query, cands, forms=forms), cands):
                np.testing.assert_array_equal(m, match_ratio(query, xb))
        assert len(made) == 3  # the query and both candidates, once each
        copy = cands[0].copy()  # equal values, another array: its own form
        np.testing.assert_array_equal(match_ratio_many(query, [copy], forms=forms)[0], match_ratio(query, copy))
        assert len(made) == 4 and len(forms._forms) == 3  # the least recently used dropped

    def test_not_bytes_takes_the_float_product(self, descs):
        from verify.matching import ByteForms

        forms = ByteForms()
        xb = descs[5] + 0.5
        np.testing.assert_array_equal(match_ratio_many(descs[55], [xb], forms=forms)[0], match_ratio(descs[55], xb))
