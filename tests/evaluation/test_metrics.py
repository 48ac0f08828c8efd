"""Metrics on hand-built cases with known answers."""

import math

import numpy as np
import pytest

from cae_lcd.evaluation.metrics import (PRCurve, best_per_query, correct_mask, pr_curve, precision_recall,
                                recall_at_k)

GT = np.array([[10, 0], [10, 1], [11, 1], [12, 2]])  # 3 queries with a true loop: 10, 11, 12


def cand(*rows):
    """rows of (query, candidate, cosine, matches, inliers) -> CANDIDATE_COLUMNS rows (temporal score = cosine,
    confidence = inliers, not accepted)."""
    r = np.array(rows, np.float64).reshape(-1, 5)
    return np.column_stack([r, r[:, 2], r[:, 4], np.zeros(len(r))])


class TestCorrectMask:
    def test_either_order_and_empty(self):
        assert correct_mask([[10, 0], [0, 10], [10, 5]], GT).tolist() == [True, True, False]
        assert correct_mask(np.zeros((0, 2)), GT).shape == (0,)


class TestPrecisionRecall:
    def test_known_counts(self):
        r = precision_recall([[10, 0], [11, 5], [12, 2]], GT)
        assert (r.true_positives, r.false_positives, r.detections, r.positives) == (2, 1, 3, 3)
        assert r.precision == pytest.approx(2 / 3) and r.recall == pytest.approx(2 / 3)

    def test_empty_detections(self):
        r = precision_recall(np.zeros((0, 2)), GT)
        assert (r.precision, r.recall, r.detections) == (1.0, 0.0, 0)

    def test_no_true_loops(self):
        r = precision_recall([[10, 0]], np.zeros((0, 2)))
        assert r.precision == 0.0 and math.isnan(r.recall) and r.as_dict()["recall"] is None

    def test_query_detected_twice_counts_once(self):
        r = precision_recall([[10, 0], [10, 1], [11, 1]], GT)  # second row of query 10 is ignored
        assert (r.true_positives, r.detections) == (2, 2)

    def test_two_true_matches_of_one_query_are_one_positive(self):
        r = precision_recall([[10, 1]], GT)
        assert r.positives == 3 and r.recall == pytest.approx(1 / 3)


class TestBestPerQuery:
    def test_inliers_then_matches_then_cosine(self):
        c = cand((10, 0, 0.9, 40, 20), (10, 1, 0.5, 50, 35), (10, 2, 0.8, 60, 35),  # tie in inliers: matches
                 (11, 1, 0.7, 30, 30), (11, 3, 0.8, 30, 30))  # tie in inliers and matches: cosine
        pairs, scores = best_per_query(c, "inliers")
        assert pairs.tolist() == [[10, 2], [11, 3]] and scores.tolist() == [35, 30]

    def test_cosine(self):
        c = cand((10, 0, 0.9, 40, 20), (10, 1, 0.5, 50, 35), (11, 1, 0.7, 30, 30))
        pairs, scores = best_per_query(c, "cosine")
        assert pairs.tolist() == [[10, 0], [11, 1]] and scores.tolist() == pytest.approx([0.9, 0.7])

    def test_min_matches_makes_candidates_ineligible(self):
        c = cand((10, 0, 0.9, 4, 4), (10, 1, 0.5, 6, 3), (11, 1, 0.7, 2, 2))
        pairs, scores = best_per_query(c, "inliers", min_matches=5)
        assert pairs.tolist() == [[10, 1]] and scores.tolist() == [3]

    def test_empty(self):
        pairs, scores = best_per_query(np.zeros((0, 6)))
        assert pairs.shape == (0, 2) and scores.shape == (0,)

    def test_unknown_score(self):
        with pytest.raises(ValueError, match="unknown score"):
            best_per_query(cand((10, 0, 0.9, 4, 4)), "area")


class TestPRCurve:
    def test_known_curve(self):
        # scores 50 (correct), 40 (false), 30 (correct); 3 positives
        c = pr_curve([[10, 0], [11, 7], [12, 2]], [50, 40, 30], GT)
        assert c.thresholds.tolist() == [50, 40, 30]
        assert c.true_positives.tolist() == [1, 1, 2] and c.detections.tolist() == [1, 2, 3]
        assert c.precision.tolist() == pytest.approx([1, 0.5, 2 / 3])
        assert c.recall.tolist() == pytest.approx([1 / 3, 1 / 3, 2 / 3])
        assert c.max_recall_at_precision_1() == (pytest.approx(1 / 3), 50.0)
        assert c.average_precision() == pytest.approx(1 / 3 * 1 + 0 * 0.5 + 1 / 3 * 2 / 3)

    def test_ties_enter_together(self):
        # a correct and a false detection share the top score: precision never reaches 1
        c = pr_curve([[10, 0], [11, 7], [12, 2]], [50, 50, 30], GT)
        assert c.thresholds.tolist() == [50, 30] and c.detections.tolist() == [2, 3]
        assert c.precision.tolist() == pytest.approx([0.5, 2 / 3])
        assert c.max_recall_at_precision_1() == (0.0, None)

    def test_all_correct(self):
        c = pr_curve([[10, 0], [11, 1], [12, 2]], [3, 2, 1], GT)
        assert c.max_recall_at_precision_1() == (1.0, 1.0) and c.average_precision() == pytest.approx(1.0)

    def test_empty_detections(self):
        c = pr_curve(np.zeros((0, 2)), np.zeros(0), GT)
        assert c.thresholds.shape == c.precision.shape == c.recall.shape == (0,)
        assert c.max_recall_at_precision_1() == (0.0, None) and c.average_precision() == 0.0
        assert c.positives == 3

    def test_no_true_loops(self):
        c = pr_curve([[10, 0]], [5], np.zeros((0, 2)))
        assert c.positives == 0 and np.isnan(c.recall).all() and c.precision.tolist() == [0.0]
        r, t = c.max_recall_at_precision_1()
        assert math.isnan(r) and t is None and math.isnan(c.average_precision())
        assert c.as_dict()["recall"] == [None]

    def test_length_mismatch(self):
        with pytest.raises(ValueError):
            pr_curve([[10, 0]], [1, 2], GT)

    def test_operating_point_is_on_the_curve(self):
        # the curve at threshold min_inliers equals precision_recall of what the detector accepts
        rng = np.random.default_rng(0)
        c = cand(*[(q, j, rng.random(), rng.integers(0, 60), rng.integers(0, 60)) for q in range(60, 80)
                   for j in rng.choice(20, 4, replace=False)])
        c[:, 4] = np.minimum(c[:, 4], c[:, 3])  # inliers <= matches
        gt = np.array([[q, q - 60] for q in range(60, 80)] + [[q, q - 59] for q in range(60, 79)])
        pairs, scores = best_per_query(c, "inliers", min_matches=5)
        curve = pr_curve(pairs, scores, gt)
        mi = 30
        accepted = pairs[scores >= mi]
        op = precision_recall(accepted, gt)
        k = np.flatnonzero(curve.thresholds >= mi)[-1]
        assert curve.detections[k] == op.detections and curve.true_positives[k] == op.true_positives


class TestRecallAtK:
    def test_known(self):
        c = cand((10, 5, 0.9, 0, 0), (10, 0, 0.8, 0, 0),  # true at rank 2
                 (11, 1, 0.95, 0, 0),  # true at rank 1
                 (12, 3, 0.9, 0, 0), (12, 4, 0.8, 0, 0), (12, 5, 0.7, 0, 0), (12, 6, 0.6, 0, 0),
                 (12, 7, 0.5, 0, 0), (12, 2, 0.4, 0, 0),  # true at rank 6
                 (13, 3, 0.9, 0, 0))  # no true loop: not in the denominator
        assert recall_at_k(c, GT, (1, 2, 5, 10)) == pytest.approx({1: 1 / 3, 2: 2 / 3, 5: 2 / 3, 10: 1.0})

    def test_order_by_score_not_by_row(self):
        c = cand((10, 5, 0.1, 0, 0), (10, 0, 0.8, 0, 0))
        assert recall_at_k(c, GT, (1,))[1] == pytest.approx(1 / 3)

    def test_ties_keep_input_order(self):
        c = cand((10, 5, 0.8, 0, 0), (10, 0, 0.8, 0, 0))
        assert recall_at_k(c, GT, (1, 2)) == pytest.approx({1: 0.0, 2: 1 / 3})

    def test_empty_candidates_and_no_true_loops(self):
        assert recall_at_k(np.zeros((0, 6)), GT) == {1: 0.0, 5: 0.0, 10: 0.0}
        r = recall_at_k(cand((10, 0, 0.9, 0, 0)), np.zeros((0, 2)), (1,))
        assert math.isnan(r[1])

    def test_duplicate_true_candidates_count_once(self):
        c = cand((10, 0, 0.9, 0, 0), (10, 1, 0.8, 0, 0))
        assert recall_at_k(c, GT, (2,))[2] == pytest.approx(1 / 3)
