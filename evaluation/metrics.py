"""Loop-closure metrics counted per query, as the literature does.

A detection is a ``(query, match)`` pair, at most one per query. It is correct when the pair is in the ground
truth. ``precision = correct / detections``; ``recall = queries with a correct detection / queries that have at
least one true loop``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["PRResult", "precision_recall"]


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
    positives = len(np.unique(gt.max(1))) if len(gt) else 0
    tp = int(correct.sum())
    fp = int(len(det) - tp)
    precision = tp / len(det) if len(det) else 1.0
    recall = tp / positives if positives else float("nan")
    return PRResult(precision, recall, tp, fp, len(det), positives)
