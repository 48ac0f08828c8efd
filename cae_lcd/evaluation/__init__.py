"""How good is a detector on data with ground truth: per-query precision/recall, PR curves, retrieval recall@k."""

from .metrics import PRCurve, PRResult, best_per_query, pr_curve, precision_recall, recall_at_k

__all__ = ["PRCurve", "PRResult", "best_per_query", "pr_curve", "precision_recall", "recall_at_k"]
