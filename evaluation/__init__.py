"""How good is a detector on data with ground truth: per-query precision/recall, PR curves, retrieval recall@k."""

from .metrics import PRResult, precision_recall

__all__ = ["PRResult", "precision_recall"]
