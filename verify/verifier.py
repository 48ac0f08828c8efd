"""Judging candidate pairs: a verifier matches descriptors (subclass) and runs the geometric check once (base).

Subclasses implement only ``match_many``; the base class turns matches into points, runs ``GeometricVerifier``
and reports a ``Verification`` per candidate. New matchers plug in by name through ``VERIFIERS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from cae.conf import Registry, merge_conf

from .features import Features
from .geometry import GeometricVerifier, GeometryResult
from .matching import match_ratio_many

__all__ = ["NOT_CHECKED", "Verification", "Verifier", "RatioTestVerifier", "VERIFIERS", "create_verifier"]


NOT_CHECKED = -1  #: inlier count of a candidate whose geometry was not checked (it could not pass or win)


@dataclass
class Verification:
    matches: int  #: putative matches after the ratio test (and mutual check)
    inliers: int  #: geometric inliers (0 when geometry is off or fails; NOT_CHECKED when it did not run)
    geometry: GeometryResult = field(repr=False)
    pairs: np.ndarray = field(repr=False)  #: (matches, 2) int64 (query_index, candidate_index)


class Verifier:
    """Base: ``verify(query, candidates, K)``; subclasses provide ``match_many``."""

    default_conf: dict[str, Any] = {}

    def __init__(self, conf: dict[str, Any] | None = None, geometry: dict[str, Any] | None = None) -> None:
        self.conf = merge_conf(self.default_conf, conf, "matching")
        self.geometry = GeometricVerifier(geometry)

    def match_many(self, query: Features, candidates: Sequence[Features]) -> list[np.ndarray]:
        """Putative matches of ``query`` against each candidate, ``(M_i, 2)`` int64 each."""
        raise NotImplementedError

    def verify(self, query: Features, candidates: Sequence[Features], K: np.ndarray | None = None,
               min_matches: int = 0, min_inliers: int = 0, check_all: bool = True) -> list[Verification]:
        """Matches, then checks geometry for each candidate that could still matter.

        Args:
            query: the query frame's features.
            candidates: features of each candidate keyframe.
            K: ``(3, 3)`` intrinsics (both frames from the same camera), or None.
            min_matches: no geometric check for fewer putative matches (the pair cannot pass anyway).
            min_inliers: likewise, and lets the geometric check stop early on a pair that cannot reach it.
            check_all: False = branch and bound: candidates are checked in decreasing match count, and one whose
                matches are fewer than the best inlier count so far is not checked (inliers <= matches, so it
                cannot win). The best candidate, and so the accepted loop, is the same either way.

        Returns:
            One ``Verification`` per candidate, in the input order; ``inliers == NOT_CHECKED`` (-1) where no
            geometric check ran. ``[]`` for no candidates.
        """
        if not candidates:
            return []
        all_pairs = self.match_many(query, candidates)
        out: list[Verification | None] = [None] * len(candidates)
        order = np.argsort([-len(p) for p in all_pairs], kind="stable")
        best = -1
        for i in order:
            pairs = all_pairs[i]
            if len(pairs) < max(min_matches, min_inliers, 1) or (not check_all and best > len(pairs)):
                geo = GeometryResult(NOT_CHECKED, np.zeros(len(pairs), bool), "not checked")
            else:
                geo = self.geometry(query.keypoints[pairs[:, 0]], candidates[i].keypoints[pairs[:, 1]], K,
                                    min_inliers)
                best = max(best, geo.inliers)
            out[i] = Verification(len(pairs), geo.inliers, geo, pairs)
        return out  # type: ignore[return-value]


VERIFIERS: Registry[Verifier] = Registry("matcher")


@VERIFIERS.register("ratio")
class RatioTestVerifier(Verifier):
    """Nearest neighbour + Lowe's ratio test (L2 for float descriptors, Hamming for binary ones)."""

    default_conf: dict[str, Any] = {
        "name": "ratio",  # matcher, by registry name
        "ratio": 0.8,  # Lowe's ratio: keep a match when d1 < ratio * d2
        "mutual": False,  # also require mutual nearest neighbours
    }

    def match_many(self, query: Features, candidates: Sequence[Features]) -> list[np.ndarray]:
        metric = "hamming" if query.descriptors.dtype == np.uint8 else "l2"
        return match_ratio_many(query.descriptors, [c.descriptors for c in candidates], self.conf["ratio"],
                                self.conf["mutual"], metric)


def create_verifier(matching: dict[str, Any] | None = None, geometry: dict[str, Any] | None = None) -> Verifier:
    """The verifier named by ``matching["name"]`` (default ``"ratio"``)."""
    return VERIFIERS.get((matching or {}).get("name", "ratio"))(matching, geometry)
