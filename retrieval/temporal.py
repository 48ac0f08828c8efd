"""Temporal consistency: one frame's candidates judged with the frames before it (a sequence of matches).

A true revisit is a stretch of frames that match a stretch of the map in order; a look-alike place matches one
frame. A temporal filter turns the single-frame candidates of each query into *hypotheses* ``(query, keyframe)``
with a score that uses the recent past. Filters plug in by name (conf section ``temporal``):

- ``sequence``: the mean similarity along a straight line of the query-vs-map similarity matrix over the last
  ``length`` frames (SeqSLAM's constant-velocity sequence match), one line per velocity in ``velocities``. Its
  hypotheses are the current candidates plus the recent frames' candidates carried forward at each velocity, so a
  loop keeps its hypothesis while single-frame retrieval misses it. Missing terms (gated frames, the map's start)
  count as 0, so a short sequence never scores like a long one.
- ``none``: the single-frame cosine score (the paper).
- ``bayes``: MILD's Bayesian filter (Han & Fang 2017, eq. 4-7; clean-room from the paper): one hypothesis per
  earlier keyframe plus "no loop"; the prediction spreads each hypothesis over its neighbours ``[i-2, i+2]``
  (probability ``stay``) or back to "no loop"; the likelihood of hypothesis ``i`` is the z-score of its similarity
  in the current row (mean and standard deviation of the row) where it exceeds one standard deviation, else 1,
  and a constant for "no loop". The filter spreads a loop over neighbouring keyframes, so a place, not one keyframe,
  holds its probability: a hypothesis that is the posterior's peak within ``score_window`` keyframes scores the
  posterior summed over them, any other its own posterior. MILD declares a loop above 0.7 (``policy.min_seq_score``).

The interface, shapes included::

    filt.update(query_id, candidate_ids (m,) int64, source) -> (hypothesis_ids (h,) int64, scores (h,) float32)
    filt.commit(query_id, kept_ids (j,) int64)     # the hypotheses the caller kept (carried to later frames)
    filt.score(query_ids (n,), ref_ids (n,), source, speed=1.0) -> (n,) float32   # any pairs (the calibration's null);
                                                                             # speed: the lines' velocities scaled
                                                                             # (one, or (n,) one a pair)

``source`` is a ``SimilaritySource`` (``CodeTable``: normalised codes by frame id): ``pairs(queries (n,), refs (n,)) -> (n,) float32`` similarities of stored
frames (NaN where a frame is not stored) and ``searchable(refs (n,)) -> (n,) bool``. Hypotheses come back best
first; an empty candidate list with no recent history gives ``(0,)`` arrays.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Callable, Protocol

import numpy as np

from cae_lcd.core.conf import Float, Floats, Int, Registry, configure

__all__ = ["SimilaritySource", "CodeTable", "TemporalFilter", "SequenceFilter", "NoFilter", "BayesFilter",
           "FILTERS", "create_filter", "GRAM_MAX", "PAIR_CHUNK"]

PAIR_CHUNK = 2048  #: pairs a filter scores in one call where many are scored at once (a calibration's far-side
#   lines, a refit's recorded frames): their similarities read in bulk, the memory bounded (a table without a Gram
#   matrix gathers ``PAIR_CHUNK x length`` code pairs at once, about 40 MB at 256 dimensions)
MEMO_DISTINCT = 64  #: pairs to compute from which a memoised ``CodeTable`` first finds the distinct ones
GRAM_MAX = 4096  #: frames up to which ``CodeTable.fixed`` keeps every pair's similarity (64 MB at most)


class SimilaritySource(Protocol):
    def pairs(self, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
        """Similarity of each ``(queries[i], refs[i])``; NaN where either frame is not stored."""

    def searchable(self, refs: np.ndarray) -> np.ndarray:
        """True where the keyframe may be returned as a loop for the current query."""


class CodeTable:
    """Normalised codes by frame id, as a ``temporal.SimilaritySource`` (NaN for frames not stored).

    Args:
        dim: code length.
        searchable: which keyframes the current query may match (None: every stored one).
        dtype: how the codes are kept: ``float16`` halves the memory and is exact for codes already rounded to
            float16 precision (``places.CodePlaces.entry``): similarities are computed in float32 either way.
        memo: keep every pair's similarity once computed (an ``(n, n)`` float32 table, up to ``GRAM_MAX`` frames),
            for a table that is scored many times and not added to meanwhile (a refit's replay: its windows read
            each pair six times over): the same values, each computed once as an unmemoised table computes it.
    """

    def __init__(self, dim: int, searchable: Callable[[np.ndarray], np.ndarray] | None = None,
                 dtype: type = np.float32, memo: bool = False) -> None:
        self.dim = dim
        self._rows: dict[int, int] = {}
        self._codes = np.zeros((0, dim), dtype)
        self._ids = np.zeros(0, np.int64)  # row -> frame id
        self._n = 0
        self._ascending = True  # ids added in increasing order (a stream's): rows found by bisection (``_find``)
        self._gram: np.ndarray | None = None  # ``fixed``: every pair's similarity, ``(n, n)`` float32
        self._memo_on = memo
        self._memo: np.ndarray | None = None  # ``memo``: the pairs computed so far, ``(n, n)`` float32, NaN: not yet
        self._searchable = searchable

    @classmethod
    def fixed(cls, ids: np.ndarray, codes: np.ndarray) -> "CodeTable":
        """A table of ``codes (n, dim)`` keyed by ``ids (n,)`` that does not grow (a calibration's, which scores every
        far-side line of the frames it reads): every pair's similarity read from their Gram matrix ``(n, n)``,
        computed once where ``n <= GRAM_MAX`` (``calibration.max_frames``, 2000 frames: 16 MB); the same
        similarities as a growing table's up to float32 rounding. Adding to it drops the matrix."""
        table = cls(codes.shape[1])
        for fid, code in zip(np.asarray(ids, np.int64).tolist(), codes):
            table.add(fid, code)
        if table._n <= GRAM_MAX:
            rows = table._codes[: table._n].astype(np.float32)
            table._gram = rows @ rows.T
        return table

    def add(self, frame_id: int, code: np.ndarray) -> None:
        self._gram = self._memo = None
        if self._n == len(self._codes):
            size = max(64, 2 * len(self._codes))
            grown = np.zeros((size, self.dim), self._codes.dtype)
            grown[: self._n] = self._codes[: self._n]
            self._codes, self._ids = grown, np.resize(self._ids, size)
        self._codes[self._n] = code
        self._ascending = self._ascending and (self._n == 0 or int(frame_id) > int(self._ids[self._n - 1]))
        self._ids[self._n] = int(frame_id)
        self._rows[int(frame_id)] = self._n
        self._n += 1

    def _find(self, frame_ids: np.ndarray) -> np.ndarray:
        """``(n,)`` int64: the row of each of ``frame_ids`` ``(n,)``, -1 where not stored: by subtraction where the ids
        were added one after another without a gap, by bisection where in increasing order, else one lookup each (the
        same rows)."""
        frame_ids = np.asarray(frame_ids, np.int64).reshape(-1)
        if not self._ascending:
            return np.array([self._rows.get(int(i), -1) for i in frame_ids.tolist()], np.int64)
        ids = self._ids[: self._n]
        if self._n and ids[-1] - ids[0] == self._n - 1:  # consecutive ids: the row is the id's offset
            pos = frame_ids - ids[0]
            return np.where((pos >= 0) & (pos < self._n), pos, -1)
        pos = np.minimum(np.searchsorted(ids, frame_ids), max(self._n - 1, 0))
        hit = (ids[pos] == frame_ids) if self._n else np.zeros(len(frame_ids), bool)
        return np.where(hit, pos, -1).astype(np.int64)

    def inserted(self, frame_id: int) -> None:
        """The frame became a keyframe: nothing to do, the table keeps its own copy of every code."""

    def remove_last(self, frame_id: int) -> None:
        """Undoes the last ``add`` (of ``frame_id``), e.g. when the database refused the frame."""
        if self._rows.get(int(frame_id)) == self._n - 1:
            self._gram = self._memo = None
            del self._rows[int(frame_id)]
            self._n -= 1

    def __contains__(self, frame_id: int) -> bool:
        return int(frame_id) in self._rows

    def __len__(self) -> int:
        return len(self._rows)

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """Frame ids ``(n,)`` int64 ascending and their codes ``(n, dim)`` float32 (a copy)."""
        ids = np.array(sorted(self._rows), np.int64)
        return ids, self._codes[[self._rows[int(i)] for i in ids]].astype(np.float32)

    def pairs(self, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
        rq, rr = self._find(queries), self._find(refs)
        out = np.full(len(rq), np.nan, np.float32)
        ok = (rq >= 0) & (rr >= 0)
        if ok.any() and self._gram is not None:
            out[ok] = self._gram[rq[ok], rr[ok]]
        elif ok.any() and self._memo_on and self._n <= GRAM_MAX:
            out[ok] = self._memoised(rq[ok], rr[ok])
        elif ok.any():
            out[ok] = self._products(rq[ok], rr[ok])
        return out

    def _products(self, rq: np.ndarray, rr: np.ndarray) -> np.ndarray:
        """``(m,)`` float32 similarities of the rows ``rq (m,)`` and ``rr (m,)``, each pair's own product (its value
        does not depend on the other pairs computed with it)."""
        a, b = (self._codes[r].astype(np.float32, copy=False) for r in (rq, rr))
        return np.einsum("ij,ij->i", a, b)

    def _memoised(self, rq: np.ndarray, rr: np.ndarray) -> np.ndarray:
        """``_products`` of the rows ``rq (m,)``, ``rr (m,)``, each distinct pair computed once in the table's life
        (``memo``)."""
        if self._memo is None:
            self._memo = np.full((self._n, self._n), np.nan, np.float32)
        got = self._memo[rq, rr]
        todo = np.flatnonzero(np.isnan(got))
        if len(todo) > MEMO_DISTINCT:  # many: each distinct pair once (a window's pairs repeat within a call)
            key, back = np.unique(rq[todo] * self._n + rr[todo], return_inverse=True)
            values = self._products(key // self._n, key % self._n)
            self._memo[key // self._n, key % self._n] = values
            got[todo] = values[back.reshape(-1)]
        elif len(todo):  # a few: computed as they come
            got[todo] = self._memo[rq[todo], rr[todo]] = self._products(rq[todo], rr[todo])
        return got

    def searchable(self, refs: np.ndarray) -> np.ndarray:
        refs = np.asarray(refs, np.int64)
        if self._searchable is not None:
            return self._searchable(refs)
        return np.array([int(r) in self._rows for r in refs], bool)


class TemporalFilter:
    """Base: ``update`` one query at a time, in frame order; ``reset`` forgets the history."""

    default_conf: dict[str, Any] = {"name": ""}
    conf_rules: dict[str, Any] = {}
    replays_history = False  #: True: the state depends on every ``update``, so a resume replays them (not only
    #                            ``commit``)

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "temporal")

    def update(self, query_id: int, candidate_ids: np.ndarray,
               source: SimilaritySource) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def commit(self, query_id: int, kept_ids: np.ndarray) -> None:
        """Records the hypotheses kept for ``query_id`` (a resumed run replays its stored ones here)."""

    def reset(self) -> None:
        """Forgets the recent history (e.g. after a gap in the stream)."""

    def score(self, query_ids: np.ndarray, ref_ids: np.ndarray, source: SimilaritySource,
              speed: float = 1.0) -> np.ndarray:
        """The filter's score of given ``(query, keyframe)`` pairs, ``(n,)`` -> ``(n,)`` (calibration uses it), on
        lines at ``speed`` times the filter's own velocities (a revisit that many times as fast as the map: the score
        path's lines at ``calibration.score_speeds``, ``retrieval.decision.ScoreSpans``; one speed, or ``(n,)`` one a
        pair, every speed's lines scored in one call); a filter without lines ignores it."""
        raise NotImplementedError


FILTERS: Registry[TemporalFilter] = Registry("temporal filter")


@FILTERS.register("none")
class NoFilter(TemporalFilter):
    """Single-frame scores: the hypotheses are the candidates themselves."""

    default_conf: dict[str, Any] = {"name": "none"}  # temporal filter, by registry name

    def update(self, query_id: int, candidate_ids: np.ndarray,
               source: SimilaritySource) -> tuple[np.ndarray, np.ndarray]:
        ids = np.asarray(candidate_ids, np.int64).reshape(-1)
        return _ranked(ids, self.score(np.full(len(ids), query_id), ids, source))

    def score(self, query_ids: np.ndarray, ref_ids: np.ndarray, source: SimilaritySource,
              speed: float = 1.0) -> np.ndarray:
        return np.nan_to_num(source.pairs(np.asarray(query_ids, np.int64), np.asarray(ref_ids, np.int64)), nan=0.0)


@FILTERS.register("sequence")
class SequenceFilter(TemporalFilter):
    """Constant-velocity sequence matching with hypotheses carried forward (see the module doc)."""

    default_conf: dict[str, Any] = {
        "name": "sequence",  # temporal filter, by registry name
        "length": 10,  # frames in a sequence match (the query and the length - 1 before it)
        "velocities": [1.0],  # map frames advanced per query frame, one hypothesis line each (-1: reverse revisit);
        #                      several positive ones cost the score path its precision (KITTI 90 at 64x32, [1, 2,
        #                      3]: 0.775; the detector warns): runs take theirs from calibration.speeds and
        #                      calibration.score_speeds
        "max_hypotheses": 64,  # hypotheses kept per query, best first
    }
    conf_rules: dict[str, Any] = {"length": Int(1, 1000), "velocities": Floats(-10, 10),
                                  "max_hypotheses": Int(1, 100_000)}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        self._recent: deque[tuple[int, np.ndarray]] = deque(maxlen=self.conf["length"])
        self._steps = np.arange(self.conf["length"], dtype=np.float64)

    def reset(self) -> None:
        self._recent.clear()

    def update(self, query_id: int, candidate_ids: np.ndarray,
               source: SimilaritySource) -> tuple[np.ndarray, np.ndarray]:
        cands = np.unique(np.asarray(candidate_ids, np.int64).reshape(-1))
        carried = [np.rint(ids + v * (query_id - fid)).astype(np.int64)
                   for fid, ids in self._recent if query_id - fid < self.conf["length"]
                   for v in self.conf["velocities"]]
        hyp = np.unique(np.concatenate([cands, *carried])) if carried else cands
        hyp = hyp[(hyp >= 0) & (hyp < query_id)]
        if len(hyp):
            hyp = hyp[source.searchable(hyp)]
        ids, scores = _ranked(hyp, self.score(np.full(len(hyp), query_id, np.int64), hyp, source))
        keep = self.conf["max_hypotheses"]
        return ids[:keep], scores[:keep]

    def commit(self, query_id: int, kept_ids: np.ndarray) -> None:
        self._recent.append((int(query_id), np.asarray(kept_ids, np.int64).reshape(-1).copy()))

    def score(self, query_ids: np.ndarray, ref_ids: np.ndarray, source: SimilaritySource,
              speed: float | np.ndarray = 1.0) -> np.ndarray:
        """``max over v of (1/length) * sum_i sim(q - i, round(r - speed*v*i))``; unknown terms count 0; ``speed``
        one for every pair or ``(n,)`` one each."""
        q = np.asarray(query_ids, np.int64).reshape(-1, 1)
        r = np.asarray(ref_ids, np.int64).reshape(-1, 1)
        if len(q) == 0:
            return np.zeros(0, np.float32)
        speed = np.asarray(speed, np.float64).reshape(-1, 1) if np.ndim(speed) else speed
        best = np.full(len(q), -np.inf)
        qs = (q - self._steps.astype(np.int64)).ravel()  # the query and the frames before it, for every pair
        for v in self.conf["velocities"]:
            rs = np.rint(r - speed * v * self._steps).astype(np.int64).ravel()
            sims = np.full(len(qs), np.nan, np.float32)
            ok = (qs >= 0) & (rs >= 0) & (rs < qs)
            sims[ok] = source.pairs(qs[ok], rs[ok])
            total = np.nan_to_num(sims, nan=0.0).reshape(len(q), -1).sum(1) / len(self._steps)
            best = np.maximum(best, total)
        return best.astype(np.float32)


@FILTERS.register("bayes")
class BayesFilter(TemporalFilter):
    """MILD's Bayesian filter over loop hypotheses (see the module doc). ``update`` wants every searchable keyframe
    as a candidate (the whole similarity row); hypotheses come back with their posterior, best first."""

    default_conf: dict[str, Any] = {
        "name": "bayes",  # temporal filter, by registry name
        "stay": 0.9,  # probability that a loop hypothesis continues (to itself or a neighbour); MILD: 0.9
        "neighbourhood": 2,  # a hypothesis moves to keyframes at most this far (MILD: [i-2, i+2])
        "no_loop_likelihood": 1.0,  # likelihood of "no loop" (MILD: a constant)
        "score_window": 2,  # a posterior peak scores the posterior summed over keyframes at most this far (0: its own)
        "max_hypotheses": 64,  # hypotheses returned per query, best first
    }
    conf_rules: dict[str, Any] = {"stay": Float(0, 1, lo_open=True, hi_open=True), "neighbourhood": Int(0, 100),
                                  "no_loop_likelihood": Float(0, lo_open=True), "score_window": Int(0, 100),
                                  "max_hypotheses": Int(1, 100_000)}
    replays_history = True

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        self.reset()

    def reset(self) -> None:
        self._ids = np.zeros(0, np.int64)  # keyframes with a hypothesis, ascending
        self._post = np.zeros(0)  # their posterior
        self._no_loop = 1.0  # posterior of "no loop"

    def _predict(self, ids: np.ndarray) -> tuple[np.ndarray, float]:
        """Prior over ``ids`` (the current keyframes) and "no loop", from the last posterior."""
        old = np.zeros(len(ids))
        if len(self._ids):
            old[np.searchsorted(ids, self._ids)] = self._post
        spread = _window(old, self.conf["neighbourhood"], np.max)
        stay = self.conf["stay"]
        prior = stay * spread + (1 - stay) * self._no_loop / max(len(ids), 1)
        prior_none = stay * self._no_loop + (1 - stay) * (1 - self._no_loop)
        return prior, prior_none

    def update(self, query_id: int, candidate_ids: np.ndarray,
               source: SimilaritySource) -> tuple[np.ndarray, np.ndarray]:
        ids = np.unique(np.asarray(candidate_ids, np.int64).reshape(-1))
        ids = ids[(ids >= 0) & (ids < query_id)]
        if len(ids):
            ids = ids[source.searchable(ids)]
        if len(ids) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.float32)
        ids = np.union1d(ids, self._ids[self._ids < query_id]).astype(np.int64)
        sims = np.nan_to_num(source.pairs(np.full(len(ids), query_id, np.int64), ids), nan=0.0)
        std = sims.std()
        z = (sims - sims.mean()) / std if std > 0 else np.zeros(len(sims))
        likelihood = np.where(z > 1.0, z, 1.0)
        prior, prior_none = self._predict(ids)
        post = likelihood * prior
        none = self.conf["no_loop_likelihood"] * prior_none
        total = post.sum() + none
        self._ids, self._post, self._no_loop = ids, post / total, none / total
        w = self.conf["score_window"]
        peak = self._post >= _window(self._post, w, np.max)  # a place: a posterior peak and its neighbours
        ranked_ids, ranked = _ranked(ids, np.where(peak, _window(self._post, w, np.sum), self._post))
        return ranked_ids[: self.conf["max_hypotheses"]], ranked[: self.conf["max_hypotheses"]]

    def score(self, query_ids: np.ndarray, ref_ids: np.ndarray, source: SimilaritySource,
              speed: float = 1.0) -> np.ndarray:
        """The similarity itself: a posterior depends on the whole history, not on one pair."""
        return np.nan_to_num(source.pairs(np.asarray(query_ids, np.int64), np.asarray(ref_ids, np.int64)), nan=0.0)


def _window(values: np.ndarray, radius: int, reduce: Callable[..., np.ndarray]) -> np.ndarray:
    """``reduce`` (max or sum) of ``values`` over positions ``[i - radius, i + radius]`` (zero beyond the ends)."""
    if radius == 0 or len(values) == 0:
        return values
    padded = np.pad(values, radius)
    return reduce(np.stack([padded[i:i + len(values)] for i in range(2 * radius + 1)]), axis=0)


def _ranked(ids: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort((ids, -scores))  # best first; equal scores: older keyframe first (deterministic)
    return ids[order].astype(np.int64), scores[order].astype(np.float32)


def create_filter(conf: dict[str, Any] | None = None) -> TemporalFilter:
    """The filter named by ``conf["name"]`` (default ``"sequence"``)."""
    return FILTERS.get((conf or {}).get("name", "sequence"))(conf)
