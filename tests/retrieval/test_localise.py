"""``retrieval.localise``: an accepted loop's keyframe walked to where the query stands, on the bundled sample.

The sample's first pass (frames 0-49) is the map, one frame every 2.9 m along a road; frame 57 of its second pass
stands at keyframe 7 (237 inliers; 5: 31, 9: 71).
"""

import pytest

from retrieval.localise import Localiser
from verify.verifier import RatioTestMatcher

QUERY, PLACE = 57, 7


@pytest.fixture
def walker(sift_features, sample_K):
    """``(Localiser, adjacent, verified pairs)`` over the sample's first pass, counting the checks it asks for."""
    matcher, asked = RatioTestMatcher(), []

    def verify(a, b):
        asked.append(1)
        return matcher.verify(a, [b], sample_K)[0]

    def adjacent(ref, step):
        nxt = ref + step
        return nxt if 0 <= nxt < 50 else None

    return Localiser(verify, sift_features), adjacent, asked


def _check(sift_features, sample_K, ref):
    return RatioTestMatcher().verify(sift_features(QUERY), [sift_features(ref)], sample_K)[0]


def test_a_keyframe_behind_the_query_is_walked_to_its_place(walker, sift_features, sample_K):
    loc, adjacent, _ = walker
    named, walked = loc.walk(sift_features(QUERY), 5, _check(sift_features, sample_K, 5), adjacent, lambda r: True)
    assert named == PLACE
    assert [r for r, _ in walked] == [6, 7, 8]  # 8: the scale change turned


def test_a_keyframe_ahead_is_walked_back(walker, sift_features, sample_K):
    loc, adjacent, _ = walker
    named, _ = loc.walk(sift_features(QUERY), 9, _check(sift_features, sample_K, 9), adjacent, lambda r: True)
    assert named == PLACE


def test_a_loop_at_its_place_does_not_walk(walker, sift_features, sample_K):
    """0.08 octaves, under half the map's step (0.22), and 237 inliers, more than keyframes 7 and 8 share (102)."""
    loc, adjacent, asked = walker
    named, walked = loc.walk(sift_features(QUERY), PLACE, _check(sift_features, sample_K, PLACE), adjacent,
                             lambda r: True)
    assert (named, walked) == (PLACE, [])
    assert len(asked) == 1  # the map's step at 7, once
    loc.walk(sift_features(QUERY), PLACE, _check(sift_features, sample_K, PLACE), adjacent, lambda r: True)
    assert len(asked) == 1  # cached


def test_a_neighbour_within_a_step_is_climbed_to_the_place(walker, sift_features, sample_K):
    """Keyframe 8 (145 inliers, 2.9 m) reads -0.15 octaves, within the map's step (0.21) but past half of it: the
    neighbour it points to (7, 237 inliers) is verified and named; 6 (85) holds fewer beyond their noise."""
    loc, adjacent, _ = walker
    named, walked = loc.walk(sift_features(QUERY), 8, _check(sift_features, sample_K, 8), adjacent, lambda r: True)
    assert named == PLACE and [r for r, _ in walked] == [7, 6]


def test_a_sparse_map_names_the_keyframe_nearest_the_query(sift_features, sample_K):
    """A map of every third keyframe (8.7 m apart: a revisit at a third of the map's speed): query 59 stands at
    keyframe 9 (251 inliers, 1 m); the accepted 6 (31 inliers, 12 m off) reads 0.31 octaves, within the map's step
    (0.35), and 12 (35 inliers) reads -0.28: each is climbed to 9."""
    def adjacent(ref, step):
        nxt = ref + 3 * step
        return nxt if 0 <= nxt < 50 else None

    loc = Localiser(lambda a, b: RatioTestMatcher().verify(a, [b], sample_K)[0], sift_features)
    for accepted in (6, 12):
        check = RatioTestMatcher().verify(sift_features(59), [sift_features(accepted)], sample_K)[0]
        named, walked = loc.walk(sift_features(59), accepted, check, adjacent, lambda r: True)
        assert named == 9 and walked[0][0] == 9
        assert loc.walk(sift_features(59), accepted, check, adjacent, lambda r: r != 9)[0] == accepted  # 9 barred


def test_a_place_among_keyframes_the_query_may_not_match_names_none(walker, sift_features, sample_K):
    """A revisit faster than the map: the place lies inside the exclusion window; the accepted keyframe sees the
    same scene from behind."""
    loc, adjacent, _ = walker
    named, walked = loc.walk(sift_features(QUERY), 5, _check(sift_features, sample_K, 5), adjacent, lambda r: r < 7)
    assert named is None and [r for r, _ in walked] == [6]


def test_walks_no_further_than_max_steps(sift_features, sample_K, walker):
    _, adjacent, _ = walker
    loc = Localiser(lambda a, b: RatioTestMatcher().verify(a, [b], sample_K)[0], sift_features, max_steps=1)
    named, walked = loc.walk(sift_features(QUERY), 5, _check(sift_features, sample_K, 5), adjacent, lambda r: True)
    assert named is None and len(walked) == 1


def test_known_checks_are_not_repeated(walker, sift_features, sample_K):
    loc, adjacent, asked = walker
    known = {r: _check(sift_features, sample_K, r) for r in (6, 7, 8)}
    named, _ = loc.walk(sift_features(QUERY), 5, _check(sift_features, sample_K, 5), adjacent, lambda r: True, known)
    assert named == PLACE and len(asked) == 1  # the map's step only


def test_a_candidate_that_cannot_hold_more_is_not_verified(sift_features, sample_K):
    """Climbing from 6 to 9 on the sparse map, 12 is a candidate whose check did not run: its matches (no more than
    9's inliers) bound its inliers, so it is not verified."""
    import dataclasses

    asked = []

    def verify(a, b):
        asked.append(1)
        return RatioTestMatcher().verify(a, [b], sample_K)[0]

    def adjacent(ref, step):
        nxt = ref + 3 * step
        return nxt if 0 <= nxt < 50 else None

    unchecked = dataclasses.replace(verify(sift_features(59), sift_features(12)), inliers=-1)
    asked.clear()
    loc = Localiser(verify, sift_features)
    check = RatioTestMatcher().verify(sift_features(59), [sift_features(6)], sample_K)[0]
    named, walked = loc.walk(sift_features(59), 6, check, adjacent, lambda r: True, {12: unchecked})
    assert named == 9 and [r for r, _ in walked] == [9]
    assert len(asked) == 2  # the map's step at 6, and keyframe 9
