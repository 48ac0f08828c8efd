"""Loop-closure metrics counted per query, as the literature does.

A detection is a ``(query, match)`` pair, at most one per query. It is correct when the pair is in the ground
truth. ``precision = correct / detections``; ``recall = queries with a correct detection / queries that have at
least one true loop``.

- ``precision_recall``: the operating point (the accepted loops).
- ``best_per_query`` + ``pr_curve``: the curve obtained by sweeping a threshold over each query's best score
  (inliers or cosine); ``PRCurve.max_recall_at_precision_1`` and ``PRCurve.average_precision`` (the AUC,
  step-wise average precision).
- ``recall_at_k``: Recall@k of the retrieval stage alone, before verification.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from retrieval.run_folder import CANDIDATE_COLUMNS

__all__ = ["PRResult", "PRCurve", "SCORES", "best_per_query", "correct_mask", "pr_curve", "precision_recall",
           "queries_with_loop", "recall_at_k"]


@dataclass
class PRResult:
    precision: float  #: correct / detections; 1.0 when there are no detections
    recall: float  #: queries with a correct detection / queries with a true loop; nan when none has one
    true_positives: int
    false_positives: int
    detections: int
    positives: int  #: queries that have at least one true loop

    def as_dict(self) -> dict:
        d = asdict(self)
        return {k: (None if isinstance(v, float) and np.isnan(v) else v) for k, v in d.items()}


def _pair_keys(pairs: np.ndarray) -> np.ndarray:
    pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
    hi, lo = pairs.max(1), pairs.min(1)
    return hi * (1 << 32) + lo


def queries_with_loop(ground_truth: np.ndarray) -> int:
    """How many queries have at least one true loop in ``(P, 2)`` ``ground_truth`` (the recall denominator).

    The query of a pair is its later frame, whichever order the pair is written in.
    """
    gt = np.asarray(ground_truth, np.int64).reshape(-1, 2)
    return len(np.unique(gt.max(1))) if len(gt) else 0


def correct_mask(detections: np.ndarray, ground_truth: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: which ``(N, 2)`` detections are true pairs of ``(P, 2)`` ``ground_truth`` (either order)."""
    det = np.asarray(detections, np.int64).reshape(-1, 2)
    return np.isin(_pair_keys(det), _pair_keys(ground_truth)) if len(det) else np.zeros(0, bool)


def precision_recall(detections: np.ndarray, ground_truth: np.ndarray) -> PRResult:
    """Per-query precision and recall.

    Args:
        detections: ``(N, 2)`` int ``(query, match)``; if a query appears twice, only its first row counts.
        ground_truth: ``(P, 2)`` int true pairs (either order).

    Returns:
        ``PRResult``. Empty detections give precision 1.0 and recall 0.0 (or nan without positives).
    """
    det = np.asarray(detections, np.int64).reshape(-1, 2)
    if len(det):
        _, first = np.unique(det[:, 0], return_index=True)
        det = det[np.sort(first)]
    gt = np.asarray(ground_truth, np.int64).reshape(-1, 2)
    correct = np.isin(_pair_keys(det), _pair_keys(gt)) if len(det) else np.zeros(0, bool)
    positives = queries_with_loop(gt)
    tp = int(correct.sum())
    fp = int(len(det) - tp)
    precision = tp / len(det) if len(det) else 1.0
    recall = tp / positives if positives else float("nan")
    return PRResult(precision, recall, tp, fp, len(det), positives)


# ----------------------------------------------------------------------------------- PR curve by a swept score
SCORES = ("confidence", "inliers", "cosine", "seq_score")  #: what a PR curve can sweep


@dataclass
class PRCurve:
    """Precision and recall at every threshold of a swept score, thresholds in decreasing order.

    At threshold ``t`` a query is detected when its best candidate scores ``>= t``; queries with equal scores
    therefore enter together (ties never split).

    Attributes:
        thresholds: ``(T,)`` float64, the distinct per-query best scores, decreasing.
        precision: ``(T,)`` float64, correct / detected at each threshold.
        recall: ``(T,)`` float64, correct / ``positives`` (nan when ``positives == 0``).
        true_positives: ``(T,)`` int64.
        detections: ``(T,)`` int64.
        positives: queries that have at least one true loop.
    """

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray
    true_positives: np.ndarray
    detections: np.ndarray
    positives: int

    def max_recall_at_precision_1(self) -> tuple[float, float | None]:
        """The largest recall reached with no false positive, and the (lowest) threshold that reaches it.

        Returns:
            ``(recall, threshold)``: recall nan without positives; ``(0.0, None)`` when even the highest threshold
            lets a false positive in, or when there is no detection at all.
        """
        if self.positives == 0:
            return float("nan"), None
        clean = np.flatnonzero(self.true_positives == self.detections)
        # false positives only accumulate as the threshold drops, so the clean points are a prefix
        if len(clean) == 0 or clean[0] != 0:
            return 0.0, None
        last = clean[-1]
        if self.true_positives[last] == 0:
            return 0.0, None
        return float(self.recall[last]), float(self.thresholds[last])

    def average_precision(self) -> float:
        """Area under the curve as average precision: ``sum_k (R_k - R_{k-1}) * P_k`` over decreasing thresholds,
        ``R_0 = 0`` (a step-wise integral, no interpolation; at most the curve's maximum recall).

        Returns:
            nan without positives; 0.0 without detections.
        """
        if self.positives == 0:
            return float("nan")
        if len(self.recall) == 0:
            return 0.0
        steps = np.diff(np.concatenate([[0.0], self.recall]))
        return float(np.sum(steps * self.precision))

    def as_dict(self) -> dict:
        """JSON-ready (nan -> None)."""
        nan_to_none = lambda a: [None if np.isnan(v) else float(v) for v in a]  # noqa: E731
        return {"thresholds": self.thresholds.tolist(), "precision": nan_to_none(self.precision),
                "recall": nan_to_none(self.recall), "true_positives": self.true_positives.tolist(),
                "detections": self.detections.tolist(), "positives": self.positives}


_COL = {name: i for i, name in enumerate(CANDIDATE_COLUMNS)}
_COL["cosine"] = _COL["score"]
_TIE_BREAKS = {"confidence": ("confidence", "inliers", "seq_score"), "inliers": ("inliers", "matches", "cosine"),
               "cosine": ("cosine", "inliers"), "seq_score": ("seq_score", "cosine")}  #: sweep score first


def best_per_query(candidates: np.ndarray, score: str = "inliers",
                   min_matches: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Each query's best candidate by the sweep score, as the detector would pick it.

    Args:
        candidates: ``(C, 8)`` rows in ``CANDIDATE_COLUMNS`` order (candidates.csv).
        score: ``"confidence"``: best by (confidence, inliers, temporal score), the calibrated detector's choice, so
            the curve at its ``accept_at`` is its operating point; ``"inliers"``: best by (inliers, matches, cosine),
            the uncalibrated detector's choice; ``"cosine"``: best by (cosine, inliers); ``"seq_score"``: best by
            (temporal score, cosine).
        min_matches: candidates with fewer putative matches are ineligible (the detector's ``policy.min_matches``;
            not applied to ``"confidence"``, which already includes it).

    Returns:
        ``(Q, 2)`` int64 ``(query, candidate)`` pairs sorted by query, and ``(Q,)`` float64 their sweep scores.
        Queries without an eligible candidate are absent; empty input gives ``(0, 2)`` and ``(0,)``.

    Raises:
        ValueError: unknown ``score``.
    """
    if score not in SCORES:
        raise ValueError(f"unknown score {score!r}; choose one of {', '.join(SCORES)}")
    c = np.asarray(candidates, np.float64)
    c = c.reshape(-1, c.shape[-1]) if c.ndim == 2 else np.zeros((0, len(CANDIDATE_COLUMNS)))
    if score != "confidence":
        c = c[c[:, _COL["matches"]] >= min_matches]
    if len(c) == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.float64)
    # np.lexsort: the last key is the primary one -> query, then the sweep score, then the tie-breakers
    keys = [c[:, _COL[name]] for name in reversed(_TIE_BREAKS[score])]
    order = np.lexsort((*keys, c[:, 0]))
    c = c[order]
    last = np.flatnonzero(np.append(c[1:, 0] != c[:-1, 0], True))  # best = last of each query's group
    return c[last][:, :2].astype(np.int64), c[last][:, _COL[_TIE_BREAKS[score][0]]].astype(np.float64)


def pr_curve(detections: np.ndarray, scores: np.ndarray, ground_truth: np.ndarray,
             positives: int | None = None) -> PRCurve:
    """Per-query precision-recall curve over a swept score.

    Args:
        detections: ``(Q, 2)`` int ``(query, match)``, one per query (e.g. from ``best_per_query``).
        scores: ``(Q,)`` the score each detection is thresholded on (higher = more confident).
        ground_truth: ``(P, 2)`` int true pairs (either order).
        positives: recall denominator; None = queries with at least one true loop in ``ground_truth``.

    Returns:
        ``PRCurve`` with one point per distinct score; all arrays ``(0,)`` when there is no detection.
    """
    det = np.asarray(detections, np.int64).reshape(-1, 2)
    s = np.asarray(scores, np.float64).reshape(-1)
    if len(s) != len(det):
        raise ValueError(f"{len(det)} detections but {len(s)} scores")
    gt = np.asarray(ground_truth, np.int64).reshape(-1, 2)
    if positives is None:
        positives = queries_with_loop(gt)
    correct = np.isin(_pair_keys(det), _pair_keys(gt)) if len(det) else np.zeros(0, bool)
    order = np.argsort(-s, kind="stable")
    s, correct = s[order], correct[order]
    ends = np.flatnonzero(np.append(s[1:] != s[:-1], True)) if len(s) else np.zeros(0, np.int64)
    tp = np.cumsum(correct)[ends].astype(np.int64)
    n_det = (ends + 1).astype(np.int64)
    precision = tp / np.maximum(n_det, 1)
    recall = tp / positives if positives else np.full(len(ends), np.nan)
    return PRCurve(s[ends], precision.astype(np.float64), np.asarray(recall, np.float64), tp, n_det, int(positives))


# --------------------------------------------------------------------------------- retrieval before verification
def recall_at_k(candidates: np.ndarray, ground_truth: np.ndarray, ks: tuple[int, ...] = (1, 5, 10)) -> dict[int, float]:
    """Recall@k of the retrieval stage alone (before verification).

    A query that has a true loop counts at ``k`` when any of its first ``k`` candidates in the run's ranking (the
    temporal score, which is the cosine score without a temporal filter; ties kept in input order) is a true pair. The denominator is every query with a true loop in ``ground_truth``, including
    queries that were gated out or had no candidate.

    Args:
        candidates: ``(C, 8)`` rows in ``CANDIDATE_COLUMNS`` order.
        ground_truth: ``(P, 2)`` int true pairs (either order).
        ks: cut-offs.

    Returns:
        ``{k: recall}``; nan for every ``k`` when no query has a true loop.
    """
    gt = np.asarray(ground_truth, np.int64).reshape(-1, 2)
    positives = queries_with_loop(gt)
    if positives == 0:
        return {int(k): float("nan") for k in ks}
    c = np.asarray(candidates, np.float64)
    if c.ndim != 2 or len(c) == 0:
        return {int(k): 0.0 for k in ks}
    order = np.lexsort((np.arange(len(c)), -c[:, _COL["seq_score"]], c[:, 0]))
    c = c[order]
    starts = np.flatnonzero(np.insert(c[1:, 0] != c[:-1, 0], 0, True))
    rank = np.arange(len(c)) - np.repeat(starts, np.diff(np.append(starts, len(c))))
    correct = np.isin(_pair_keys(c[:, :2].astype(np.int64)), _pair_keys(gt))
    first_hit: dict[int, int] = {}
    for q, r in zip(c[correct, 0].astype(np.int64), rank[correct]):
        first_hit[int(q)] = min(first_hit.get(int(q), r), r)
    hits = np.array(list(first_hit.values()), np.int64)
    return {int(k): float(np.sum(hits < k) / positives) for k in ks}
