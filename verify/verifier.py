"""Judging candidate pairs: a verifier matches descriptors (subclass) and runs the geometric check once (base).

Subclasses implement only ``match_many``; the base class turns matches into points, runs ``GeometricVerifier``
and reports a ``Verification`` per candidate. Verifiers differ only in how they match, so they are registered by
matcher name in ``MATCHERS`` and selected by the ``matcher`` section of the conf (``{"matcher": {"name":
"ratio"}}``).
"""

from __future__ import annotations

import threading
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from cae_lcd.core.conf import Bool, ConfigError, Float, Registry, configure
from cae_lcd.core.threads import in_turn

from .features import Features
from .geometry import GeometricVerifier, GeometryResult
from .matching import ByteForms, match_ratio_many

__all__ = ["NOT_CHECKED", "Verification", "Verifier", "RatioTestMatcher", "MATCHERS", "create_verifier",
           "scale_change", "MIN_SCALE_INLIERS"]


NOT_CHECKED = -1  #: inlier count of a candidate whose geometry was not checked (it could not pass or win)
MIN_SCALE_INLIERS = 8  #: inliers ``scale_change`` needs (fewer: no estimate, NaN)


@dataclass
class Verification:
    matches: int  #: putative matches after the ratio test (and mutual check)
    inliers: int  #: geometric inliers (0 when geometry is off or fails; NOT_CHECKED when it did not run)
    geometry: GeometryResult = field(repr=False)
    pairs: np.ndarray = field(repr=False)  #: (matches, 2) int64 (query_index, candidate_index)


def scale_change(query: Features, candidate: Features, check: Verification) -> float:
    """How much larger the query sees what both frames see: the median over the check's geometric inliers of
    ``log2(query scale / candidate scale)``, in octaves. Positive where the query is nearer the scene than the
    candidate (a camera that moved on toward what it looks at; or a narrower lens), about 0 at the same viewpoint.

    Args:
        query: the query frame's features (``scales (N,)``).
        candidate: the candidate's features.
        check: their ``Verification`` (``pairs (M, 2)``, ``geometry.mask (M,)``).

    Returns:
        The median in octaves; NaN where fewer than ``MIN_SCALE_INLIERS`` inliers were found (or none checked).
    """
    if check.inliers < MIN_SCALE_INLIERS:
        return float("nan")
    pairs = check.pairs[np.asarray(check.geometry.mask, bool)]
    q, c = query.scales[pairs[:, 0]].astype(np.float64), candidate.scales[pairs[:, 1]].astype(np.float64)
    ok = (q > 0) & (c > 0)
    if ok.sum() < MIN_SCALE_INLIERS:
        return float("nan")
    return float(np.median(np.log2(q[ok] / c[ok])))


class Verifier:
    """Base: ``verify(query, candidates, K)``; subclasses provide ``match_many``."""

    default_conf: dict[str, Any] = {}
    conf_rules: dict[str, Any] = {}

    def __init__(self, conf: dict[str, Any] | None = None, geometry: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "matcher")
        self.geometry = GeometricVerifier(geometry)

    def match_many(self, query: Features, candidates: Sequence[Features]) -> list[np.ndarray]:
        """Putative matches of ``query`` against each candidate, ``(M_i, 2)`` int64 each."""
        raise NotImplementedError

    def verify(self, query: Features, candidates: Sequence[Features], K: np.ndarray | None = None,
               min_matches: int = 0, min_inliers: int = 0, check_all: bool = True,
               pool: Executor | None = None) -> list[Verification]:
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
            pool: an executor whose one thread works beside the caller's (OpenCV and torch release the GIL): half
                of the matching, and the geometric checks taken in turn (``_checked_in_turn``). The same result as
                without it.

        Returns:
            One ``Verification`` per candidate, in the input order; ``inliers == NOT_CHECKED`` (-1) where no
            geometric check ran. ``[]`` for no candidates.
        """
        if not candidates:
            return []
        all_pairs = self._match_split(query, candidates, pool)
        order = [int(i) for i in np.argsort([-len(p) for p in all_pairs], kind="stable")]
        needed = max(min_matches, min_inliers, 1)
        todo = [i for i in order if len(all_pairs[i]) >= needed]

        def check(i: int) -> GeometryResult:
            pairs = all_pairs[i]
            return self.geometry(query.keypoints[pairs[:, 0]], candidates[i].keypoints[pairs[:, 1]], K, min_inliers)

        geos = _checked_in_turn(todo, [len(all_pairs[i]) for i in todo], check, check_all, pool)
        out: list[Verification | None] = [None] * len(candidates)
        best = -1
        for i in order:  # the branch and bound, in order, on the checks made (a check made ahead is dropped here)
            pairs = all_pairs[i]
            geo = geos.get(i)
            if geo is None or len(pairs) < needed or (not check_all and best > len(pairs)):
                geo = GeometryResult(NOT_CHECKED, np.zeros(len(pairs), bool), "not checked")
            else:
                best = max(best, geo.inliers)
            out[i] = Verification(len(pairs), geo.inliers, geo, pairs)
        return out  # type: ignore[return-value]

    def _match_split(self, query: Features, candidates: Sequence[Features],
                     pool: Executor | None) -> list[np.ndarray]:
        """``match_many``; with ``pool``, its thread matches the first half of the candidates meanwhile."""
        half = len(candidates) // 2
        if pool is None or half == 0:
            return self.match_many(query, candidates)
        first = pool.submit(self.match_many, query, candidates[:half])
        rest = self.match_many(query, candidates[half:])
        return first.result() + rest


def _checked_in_turn(todo: list[int], matches: list[int], check: Callable[[int], GeometryResult], check_all: bool,
                     pool: Executor | None) -> dict[int, GeometryResult]:
    """``check(i)`` for the candidates ``todo`` (in decreasing match count ``matches``), by the caller and ``pool``'s
    thread, each taking the next one in turn; one is not checked when an inlier count already found exceeds its
    matches (``check_all`` False). Every check the sequential branch and bound makes is made: the counts found
    when a candidate is taken come from earlier candidates only, and any of them that the sequential order skips
    has fewer inliers than its best so far, so a candidate skipped here is skipped there. A check made here that
    the sequential order would skip is dropped by the caller."""
    done: dict[int, GeometryResult] = {}
    state = {"next": 0, "best": -1}
    lock = threading.Lock()

    def lane() -> None:
        while True:
            with lock:
                k = state["next"]
                if k >= len(todo):
                    return
                state["next"] = k + 1
                if not check_all and state["best"] > matches[k]:
                    continue
            geo = check(todo[k])
            with lock:
                done[todo[k]] = geo
                state["best"] = max(state["best"], geo.inliers)

    in_turn(lane, pool, len(todo))
    return done


MATCHERS: Registry[Verifier] = Registry("matcher")  #: verifiers by the matcher they use (conf section ``matcher``)


@MATCHERS.register("ratio")
class RatioTestMatcher(Verifier):
    """Nearest neighbour + Lowe's ratio test, in the features' own metric (L2 for SIFT, Hamming for binary)."""

    default_conf: dict[str, Any] = {
        "name": "ratio",  # matcher, by registry name
        "ratio": 0.8,  # Lowe's ratio: keep a match when d1 < ratio * d2
        "mutual": False,  # also require mutual nearest neighbours
    }
    conf_rules: dict[str, Any] = {"ratio": Float(0, 1, lo_open=True), "mutual": Bool()}

    def __init__(self, conf: dict[str, Any] | None = None, geometry: dict[str, Any] | None = None) -> None:
        super().__init__(conf, geometry)
        self._forms = ByteForms()  # the 8-bit forms of the descriptors matched lately (keyframes matched again)

    def match_many(self, query: Features, candidates: Sequence[Features]) -> list[np.ndarray]:
        for cand in candidates:
            if cand.metric != query.metric:
                raise ConfigError(f"cannot match {query.metric} descriptors against {cand.metric} ones")
        return match_ratio_many(query.descriptors, [c.descriptors for c in candidates], self.conf["ratio"],
                                self.conf["mutual"], query.metric, self._forms)


def create_verifier(matcher: dict[str, Any] | None = None, geometry: dict[str, Any] | None = None) -> Verifier:
    """The verifier whose matcher is named by ``matcher["name"]`` (default ``"ratio"``)."""
    return MATCHERS.get((matcher or {}).get("name", "ratio"))(matcher, geometry)
