"""One calibrated decision from fused evidence (issue 17): a loop is a sequence of agreeing matches, not one pair.

The calibration (``retrieval.calibrate``) measures, on the sequence itself, what a non-loop looks like *where the
detector actually looks*: the **hard negatives** (the far-side keyframes retrieval would return for a sampled query,
verified as in the run), and what a loop looks like: the **positives** (a frame and a near neighbour). From them:

- **Pair evidence** ``e(x) = -log10 P_hard(inliers >= x)``, read from the measured null itself (``EmpiricalTail``,
  issue 27: ``(#{samples >= x} + 1) / (n + 1)``, a valid p-value by exchangeability, no tail past the sample, so one
  pair claims at most ``log10(n + 1)`` decades; ``TailModel``, an exponential tail above the median, remains for
  calibrations made by hand). ``e`` is 0 at or below the null's median.
- **Fused evidence** of a hypothesis ``(q, r)`` on the line of speed ``v`` (keyframes the map advances per query
  frame, one of ``speeds``: ``calibration.speeds``, 1x, 2x and 3x by default): ``E = e(q, r) + sum`` over the
  ``span - 1`` frames processed before ``q`` of the best ``e(q', r') - log10(2 tol + 1)`` among their verified
  candidates within ``tol`` keyframes of ``r - v (q - q')`` (the ``log10`` pays for choosing among the consistent
  ones); the best line's. At ``v = 1`` that is an offset ``q' - r'`` within ``tol`` of ``q - r``; a revisit 3x as
  fast drifts 2 frames a frame off it, so only the line of its own speed fuses its frames
  (``bench.revisit_speed``: 1 of 34 such queries found on the map's line alone, 26 with the three).
- **Its null** ``P_E``: for a run of ``m`` consecutive frames ending at the query (``m`` up to ``span``, every ``m``
  counted in the run's tests), the heavier of the Gamma(m) tail (independent pair evidence: every frame of the run
  counted, with or without support) and the tail measured on hard-negative *sequences* (the pairs ``(q - j, r - j)``
  behind each hard negative: look-alike streets look alike for several frames, and this sees it). The independence
  the Gamma tail assumes is what the stress sets check (``bench.aliasing``: KITTI 00 then its own frames mirrored, and
  00 then 07, frame after frame: 0 loops).
- **One threshold**: ``confidence = -log10(tests * P_E(E))``, ``tests`` counting every line's speed (a run is
  tested on each); a loop needs ``confidence >= accept_at``
  (``NFA <= expected_false_loops / 2``) and positive evidence of its own pair (geometry can always veto).
- **Delayed loops** (``Confirmations``): a run of ``m`` frames accepted at frame ``t`` certifies its earlier
  members: each of ``t - m + 1 .. t - 1`` with evidence on the run's offset, not yet a loop and whose pair was
  admissible then (not too recent, not a stop), is reported at ``t`` (once); a refused run certifies nothing. On the
  score path the run is ``m`` windows, ``m * length`` frames: each earlier frame of them with an admissible candidate
  on the run's line (one frame off at most: where its keyframe on the line was refused, e.g. by the stop rule, an
  admissible one beside it) and its own window localised on that line (``ScoreSpans.localised``: a line one frame
  past a revisit's start reads the revisit's windows, not the frame before it) is reported.
- **Whether one pair may decide alone**: only where geometry separates on this sequence (the median positive pair
  would be accepted alone and no hard negative is); elsewhere a loop needs evidence from ``min_support`` frames.
- **The score path fuses too** (``ScoreSpans``, where local features are too few to verify, and on a stream's inlier
  path beside it, ``both``: a candidate's confidence the larger of the two paths', each on its own budget; issue 27:
  measured, not extrapolated): the temporal score of a hypothesis is the mean similarity along a line of ``length``
  frames (a window), on lines at one of ``speeds`` (``calibration.score_speeds``, the map's and 15 % either side by
  default; window ``j`` of a line at speed ``v`` through ``(q, r)``: ``(q - j length, r - v j length)``, the filter's
  own lines scaled by ``v``; a window of a line at another speed than the map's with a still frame on either side does
  not agree: a stop has no speed), the best speed's taken, its null measured the same way and every speed counted among
  the tests. One window's evidence is its empirical p-value among the far-side pairs' window scores (``EmpiricalTail``,
  at most ``log10(n + 1)`` decades: no Gaussian tail past the sample). ``m`` consecutive windows on the same line (``m``
  up to ``span``) fuse: every window must agree (at least ``AGREE`` decades: one weak, missing or contrary window vetoes
  the longer spans), their evidence is summed, and its null is the heavier of the Gamma(m) tail (disjoint windows taken
  as independent) and the fused evidence measured on the far-side lines of ``m`` windows (``fused_log10_sf``, the inlier
  path's rule). The run's tests count every span; the confidence is the best span's. **The promise**: no window claims
  below ``1 / (n + 1)`` of its sample, and a run of ``m`` windows claims no more than ``m`` independent such windows
  would under the Gamma tail (and no more than its measured null shows where that is heavier); where the sample cannot
  certify the run's tests in one window, a loop needs several windows above every far-side pair (the calibration notes
  say how many). The line must say *where* the query is: its own window is not beaten on a line up to ``length // 2``
  frames off by more than ``LOCALISE`` decades, nor by more than ``LOCAL_SPREAD`` null spreads of raw score (a strong
  revisit saturates every nearby window's evidence; a revisit a little faster than the line drifts off it)
  (``localised``), and the stop rule holds on the query's frame and the one before (``Stops.line_admissible``). An
  accepted run certifies its earlier frames on the line (``Confirmations``, ``reach = span * length`` frames).
- **Too recent** (``Horizon``): a keyframe is not a loop while every stored frame between it and the query still
  looks like the query (cosine at least ``stretch_cos``, the adjacent frames' 10th percentile, with at most
  ``gap - 1`` dissimilar frames in a row): a slow robot stays in a place longer, a fast one leaves it sooner; the
  frame count ``search.exclude_recent`` stays the floor.
- **A stop is one place, matched to a stop** (``Stops``): frames between which the camera stood still (the code
  unchanged, cosine at least ``still_cos``) are one observation repeated, not new evidence: a robot waiting at a
  station, or in front of a shelf, would otherwise fill a whole window of agreement with one image. A query that has
  stood still for ``s`` frames (its stop so far) may therefore only be matched to a keyframe where the reference
  stood still at least as long (``s`` frames up to it): a stop matched to a stop, along the line. Where the query
  waits longer than the reference ever did there, the line (both traversals moving alike) no longer holds and the
  query's frame within the reference's passage is undetermined: no loop (the query's arrival, a moving frame, was
  decided on its own evidence). A moving query is not affected. But where the arrival *was* a loop, the stop is that
  place: each still frame after it carries the arrival's loop (``Decision.stop_carry``: to its candidate nearest
  after the loop's keyframe in the reference's own stop, which may begin ``STOP_EDGE`` frame later, with the
  arrival's confidence; nothing new is claimed; the keyframe after the loop's is kept among the frame's hypotheses
  whatever its rank, ``Decision.carry_to``: a stop's frames all look alike).

Shapes: ``Decision.code_terms(query_id, refs (m,) int64, source) -> CodeTerms`` (what the codes alone say, read
before the candidates are verified); ``Decision.confidences(query_id, refs (m,) int64, inliers (m,) int64, source,
terms=None) -> (m,) float64``; ``Decision.commit(query_id, refs (m,), inliers (m,))``.
"""

from __future__ import annotations

import copy
import functools
import math
from collections import deque
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from .temporal import PAIR_CHUNK

__all__ = ["TailModel", "EmpiricalTail", "MeasuredTail", "gamma_log10_sf", "gaussian_log10_sf", "fused_log10_sf",
           "Horizon", "Stops", "Confirmations", "ScoreSpans", "CodeTerms", "Decision", "SPAN", "TOL", "GAP",
           "UNSUPPORTED", "AGREE", "LOCALISE", "LOCAL_SPREAD"]

LN10 = math.log(10.0)
STOP_EDGE = 1  #: frames by which the reference's stop may begin after the loop's keyframe and still carry the query's
#   (``Decision.stop_carry``): where a camera slows to a stop, the first still frame is one frame uncertain either way
#   (Nordland: the winter train still from 706, after its loop 705 -> 205; the summer one from 207)
SPAN = 5  #: frames (inlier path) or windows (score path) one decision fuses at most, the query's and those before it
#           (issue 27: a measured pair null caps what one frame claims; a run of frames on one line decides)
TOL = 2  #: keyframes a fused frame's match may lie off its run's line (at the map's speed: the offset ``q - r``
#          drifting by up to this many frames)
UNSUPPORTED = -1e8  #: the confidence of an admissible pair with evidence of its own that no run supports yet (the
#                      first frame of a revisit): below any ``accept_at``, above ``Confirmations.VETO``, so that the run
#                      its next frames complete certifies it (``Confirmations``)
GAP = 3  #: dissimilar frames in a row that end the stretch the query is still in
MAX_BACK = 2000  #: frames the horizon looks back at most
LOCALISE = 1.0  #: decades by which a nearby line (reference within ``window // 2`` frames) may beat the query's own
#                 window before the score path refuses the line as not localised (``ScoreSpans.localised``)
LOCAL_SPREAD = 2.0  #: null spreads (the far-side window scores' 90th percentile above their median) by which a nearby
#   line's own window may beat the pair's in raw score before the score path refuses the pair as not localised
#   (``ScoreSpans.localised``): where a revisit is strong every nearby window saturates the null's evidence, and
#   only the raw scores still say where the query is (KITTI 90 at 64x32, its second pass at 1.15x the map's speed:
#   a run of windows on the map's line through a keyframe 4 frames behind the query's own window, which read 0.32
#   there and 0.91 two frames on; 9 loops 5-6 m off before, none now)
GAMMA_CACHE = 4096  #: ``gamma_log10_sf`` values kept (least recently used dropped)
MOVING_KEPT = 4096  #: moving frames ``Stops`` remembers as such (the oldest forgotten first)
AGREE = 1.0  #: decades a score-path window needs to agree (its own p-value <= 0.1: above the null's 90th percentile);
#              a weaker window vetoes the longer spans (earlier windows cannot carry a query whose own is noise)


@dataclass(frozen=True)
class TailModel:
    """``P(X >= x)`` of a null sample: 1 up to its median ``u``, ``0.5 exp(-(x - u) / beta)`` above."""

    u: float
    beta: float

    @classmethod
    def fit(cls, samples: np.ndarray, min_beta: float = 1.0) -> "TailModel":
        """Median, then the exponential tail's maximum-likelihood scale (mean excess over the median), widened so
        that the largest of the ``n`` samples has a tail probability of at least ``1 / (2 n)`` (checked against the
        samples themselves: a tail lighter than the data would promise false loops it cannot keep)."""
        x = np.sort(np.asarray(samples, np.float64).ravel())
        if len(x) == 0:
            return cls(0.0, min_beta)
        u = float(np.median(x))
        excess = x[x > u] - u
        beta = float(excess.mean()) if len(excess) else min_beta
        if len(x) > 1:
            beta = max(beta, (float(x[-1]) - u) / math.log(len(x)))
        return cls(u, max(beta, min_beta))

    def log10_sf(self, x: float) -> float:
        """``log10 P(X >= x)`` (0 at or below the median)."""
        return float(self.log10_sfs(np.array([x], np.float64))[0])

    def log10_sfs(self, x: np.ndarray) -> np.ndarray:
        """``log10_sf`` of every value of ``x`` ``(m,)`` -> ``(m,)``: an exponential tail above the median."""
        x = np.asarray(x, np.float64)
        return np.where(x <= self.u, 0.0, math.log10(0.5) - (x - self.u) / self.beta / LN10)

    def evidence(self, x: float) -> float:
        """``-log10 P(X >= x)``, >= 0."""
        return -self.log10_sf(x)

    def as_dict(self) -> dict[str, float]:
        return {"u": self.u, "beta": self.beta}


class EmpiricalTail:
    """``P(X >= x)`` of a null sample, claimed only as far as the sample shows: the empirical p-value
    ``(#{samples >= x} + 1) / (n + 1)`` (1 at or below the median). Under exchangeability of a new null value with the
    ``n`` samples this is a valid p-value (``P(p <= a) <= a``) without any model of the tail: conservative by
    construction. Above the largest sample it stays at ``1 / (n + 1)``: no extrapolation, so one pair can never claim
    more than ``log10(n + 1)`` decades; a loop then needs several frames of evidence (``Decision``).

    Args:
        samples: ``(n,)`` the measured null (the hard negatives' inlier counts).
    """

    def __init__(self, samples: np.ndarray) -> None:
        self.x = np.sort(np.asarray(samples, np.float64).ravel())
        self.u = float(np.median(self.x)) if len(self.x) else 0.0

    def log10_sf(self, x: float) -> float:
        """``log10 P(X >= x)`` (0 at or below the median; at least ``-log10(n + 1)``)."""
        return float(self.log10_sfs(np.array([x], np.float64))[0])

    def log10_sfs(self, x: np.ndarray) -> np.ndarray:
        """``log10_sf`` of every value of ``x`` ``(m,)`` -> ``(m,)`` (NaN counts as no evidence)."""
        x = np.asarray(x, np.float64)
        if not len(self.x):
            return np.zeros(x.shape)
        above = len(self.x) - np.searchsorted(self.x, x, "left")
        out = np.minimum(0.0, np.log10((above + 1) / (len(self.x) + 1)))
        return np.where((x <= self.u) | np.isnan(x), 0.0, out)

    def evidence(self, x: float) -> float:
        """``-log10 P(X >= x)``, >= 0 and at most ``log10(n + 1)``."""
        return -self.log10_sf(x)

    @property
    def max_evidence(self) -> float:
        """The most one value can claim: ``log10(n + 1)`` decades."""
        return math.log10(len(self.x) + 1)


class MeasuredTail:
    """What a sample of a null statistic shows of its tail, and nothing more: ``P(X >= x) = #{samples >= x} / (n + 1)``
    (``-inf`` above the largest sample). Used beside a model (``Decision.fused_log10_sf`` takes the heavier): where the
    measured null is heavier than the model (look-alike frames are not independent), it raises the bar; beyond its
    largest sample the model speaks, and the stress sets check it (``bench.aliasing``). Unlike a tail fitted to the
    sample, one large value cannot widen the null far past itself (issue 27).

    Args:
        samples: ``(n,)`` the measured statistic (the fused evidence of hard-negative sequences, decades).
    """

    def __init__(self, samples: np.ndarray) -> None:
        self.x = np.sort(np.asarray(samples, np.float64).ravel())

    def log10_sf(self, x: float) -> float:
        """``log10 P(X >= x)`` as measured (``-inf`` above the largest sample)."""
        above = len(self.x) - int(np.searchsorted(self.x, x, "left"))
        return math.log10(above / (len(self.x) + 1)) if above else -math.inf


@functools.lru_cache(maxsize=GAMMA_CACHE)
def gamma_log10_sf(k: int, decades: float) -> float:
    """``log10 P(sum of k independent -log10 p-values >= decades)`` (a Gamma(k, 1) tail in natural units). Kept for
    the values asked lately (a run's evidence sums come from an empirical null's few levels: KITTI 90 streamed asks
    1120 distinct ones 15594 times)."""
    if decades <= 0:
        return 0.0
    s = decades * LN10
    terms = [i * math.log(s) - math.lgamma(i + 1) for i in range(k)]
    top = max(terms)
    return min(0.0, (-s + top + math.log(sum(math.exp(t - top) for t in terms))) / LN10)


def gaussian_log10_sf(z: float) -> float:
    """``log10 P(Z >= z)`` for a standard normal, accurate far into the tail."""
    if z < 8:
        return math.log10(max(0.5 * math.erfc(z / math.sqrt(2.0)), 1e-300))
    return (-0.5 * z * z - math.log(z * math.sqrt(2 * math.pi))) / LN10


def fused_log10_sf(frames: int, decades: float, measured: "MeasuredTail | TailModel | None" = None) -> float:
    """``log10 P(E >= decades)`` of evidence summed over ``frames`` terms, each a valid ``-log10`` p-value: the
    heavier of the Gamma(frames) tail (independent terms) and the tail ``measured`` on null sequences of the same
    statistic (look-alike stretches are not independent: where they are heavier, they raise the bar; beyond the
    largest measured value the Gamma tail speaks). Both paths fuse with it (``Decision``, ``ScoreSpans``)."""
    gamma = gamma_log10_sf(frames, decades)
    return gamma if measured is None else max(gamma, measured.log10_sf(decades))


class ScoreSpans:
    """The score path's fused evidence (see the module doc): ``score(q, r)`` over up to ``len(measured)`` consecutive
    windows of ``window`` frames on the line through ``(q, r)`` at one of ``speeds`` (keyframes the map advances per
    query frame: window ``j`` of a line at speed ``v`` is ``(q - j window, r - v j window)``, each window scored on
    lines at ``v`` times the filter's own velocities), every window's evidence read from the measured null of one
    window (``tail``: an ``EmpiricalTail``, so one window claims at most ``log10(n + 1)`` decades) and the sum over
    ``m`` windows from ``fused_log10_sf`` with the tail measured on far-side lines of ``m`` windows (the best of the
    speeds, as the decision takes it).

    Args:
        score: the temporal filter's pair score, ``(queries (n,), refs (n,), source, speed: one or (n,)) -> (n,)``.
        window: frames one score covers (the filter's ``length``).
        tail: the null of one window's score (``EmpiricalTail`` of the far-side pairs' scores).
        measured: ``[MeasuredTail]``, one per number of windows fused ``m = 1..span``: the fused evidence of the
            far-side lines of ``m`` windows, the best of the speeds.
        tests: hypotheses the run tests (every span and speed counted).
        speeds: the lines' speeds (``calibration.score_speeds``).
        stops: the run's ``Stops``: a window of a line at another speed than the map's with a still frame on either
            side does not agree (a stop has no speed: a line at another speed reads the stop's frames at offsets the
            stop's length sets, not the motion's). None: no such rule (the calibration's null: every line, the
            heavier).
    """

    def __init__(self, score: Any, window: int, tail: "EmpiricalTail", measured: list["MeasuredTail"],
                 tests: float, speeds: tuple[float, ...] = (1.0,), stops: "Stops | None" = None) -> None:
        self.score, self.window, self.tail, self.tests = score, int(window), tail, float(tests)
        self.measured = list(measured)
        #: the null's spread: its 90th percentile above its median (raw window score; ``LOCAL_SPREAD``)
        self.spread = float(np.quantile(tail.x, 0.9) - tail.u) if len(tail.x) else 0.0
        self.speeds = tuple(float(v) for v in speeds)
        self.stops = stops
        #: ``_by_speed``'s rows since the last ``keep_rows`` (``(query, ref) -> ((span,) confidences, speed)``) and
        #: the code store they were read from: ``best_run`` reads a frame's accepted pair there (its candidates were
        #: scored by ``Decision.code_terms`` a moment before, on the same codes) instead of scoring it again
        self._rows: dict[tuple[int, int], tuple[np.ndarray, float]] = {}
        self._rows_source: Any = None

    def keep_rows(self, source: Any) -> None:
        """Forgets the rows kept so far and keeps those ``_by_speed`` computes on ``source`` from now on (a frame's
        candidates, or a replay's frames: ``Decision.code_terms_many``)."""
        self._rows, self._rows_source = {}, source

    @property
    def span(self) -> int:
        """Windows fused at most."""
        return len(self.measured)

    def windows(self, queries: np.ndarray, refs: np.ndarray, source: Any,
                speed: float | np.ndarray = 1.0) -> np.ndarray:
        """``(n, span)``: the score of each pair's window ``j`` (the pair moved back ``j * window`` query frames on its
        line at ``speed``: one for every pair, or ``(n,)`` one each, several speeds scored in one call); NaN where an
        earlier window's pair lies before the first frame (missing terms inside a window count 0, as in the filter's
        own score)."""
        queries, refs = np.asarray(queries, np.int64), np.asarray(refs, np.int64)
        speed = np.broadcast_to(np.asarray(speed, np.float64), queries.shape)
        shift = np.arange(self.span, dtype=np.int64) * self.window  # every window of every pair, one call
        qj = (queries[:, None] - shift).ravel()
        rj = (refs[:, None] - np.rint(speed[:, None] * shift).astype(np.int64)).ravel()
        vj = np.repeat(speed, self.span)
        out = np.full(len(qj), np.nan)
        ok = rj >= 0
        if ok.any():
            out[ok] = self.score(qj[ok], rj[ok], source, vj[ok])
            moving = ok & (vj != 1.0)  # lines at another speed than the map's
            if self.stops is not None and moving.any():
                out[np.flatnonzero(moving)[self._through_stop(qj[moving], rj[moving], source, vj[moving])]] = -np.inf
        return out.reshape(-1, self.span)

    def _through_stop(self, queries: np.ndarray, refs: np.ndarray, source: Any, speed: np.ndarray) -> np.ndarray:
        """``(n,)`` bool: whether the window of each ``(queries[i], refs[i])`` on its line at ``speed[i]`` holds a
        still frame (``Stops.still``) on either side."""
        steps = np.arange(self.window, dtype=np.float64)
        frames = np.concatenate([(queries[:, None] - steps.astype(np.int64)).ravel(),
                                 np.rint(refs[:, None] - speed[:, None] * steps).astype(np.int64).ravel()])
        uniq, back = np.unique(frames, return_inverse=True)  # windows of nearby pairs share most of their frames
        return self.stops.still(uniq, source)[back].reshape(2, len(queries), self.window).any(axis=(0, 2))

    def fused(self, win: np.ndarray) -> np.ndarray:
        """``(n, span)``: the fused evidence (decades) of spans 1..span, the sum of the first ``m`` windows' evidence;
        0 from the first window that does not agree (under ``AGREE`` decades, the null's 90th percentile: one weak,
        missing or contrary window vetoes the longer spans), NaN where a window is missing (before the first
        frame)."""
        ev = -self.tail.log10_sfs(win)
        agree = np.cumprod(ev >= AGREE, axis=1).astype(bool)
        return np.where(np.isnan(win), np.nan, np.where(agree, np.cumsum(ev, axis=1), 0.0))

    def fused_best(self, queries: np.ndarray, refs: np.ndarray, source: Any) -> np.ndarray:
        """``(n, span)``: ``fused`` of each pair's line at the speed where it is largest (NaN only where it is NaN at
        every speed): the statistic the decision takes, so the one whose null the calibration measures."""
        out = self.fused(self.windows(queries, refs, source, self.speeds[0]))
        for v in self.speeds[1:]:
            out = np.fmax(out, self.fused(self.windows(queries, refs, source, v)))
        return out

    def _by_speed(self, queries: np.ndarray, refs: np.ndarray, source: Any) -> tuple[np.ndarray, np.ndarray]:
        """``((n, span) -log10 NFA of each pair over 1..span windows on its best line, (n,) that line's speed)``
        (``-inf`` where no span agrees at any speed; the first speed there)."""
        n, speeds = len(queries), np.asarray(self.speeds, np.float64)
        best, speed = None, np.full(n, self.speeds[0])
        every = self.windows(np.tile(queries, len(speeds)), np.tile(refs, len(speeds)), source, np.repeat(speeds, n))
        for k, v in enumerate(self.speeds):  # every speed's windows scored in one call, read speed by speed
            fused = self.fused(every[k * n:(k + 1) * n])
            conf = np.full(fused.shape, -math.inf)
            for j, measured in enumerate(self.measured):
                for i in np.flatnonzero(np.nan_to_num(fused[:, j]) > 0):
                    conf[i, j] = -(math.log10(self.tests) + fused_log10_sf(j + 1, fused[i, j], measured))
            if best is None:
                best = conf
                continue
            better = conf.max(axis=1, initial=-math.inf) > best.max(axis=1, initial=-math.inf)
            best[better], speed[better] = conf[better], v
        if source is self._rows_source and source is not None:
            self._rows.update(zip(zip(np.asarray(queries).tolist(), np.asarray(refs).tolist()),
                                  zip(best.copy(), speed.tolist())))
        return best, speed

    def span_confidences(self, queries: np.ndarray, refs: np.ndarray, source: Any) -> np.ndarray:
        """``(n, span)`` ``-log10 NFA`` of each pair over 1..span windows on its best line (``-inf`` where that span
        does not agree)."""
        return self._by_speed(queries, refs, source)[0]

    def localised(self, queries: np.ndarray, refs: np.ndarray, source: Any, speed: float = 1.0) -> np.ndarray:
        """``(n,)`` bool: whether the query's own window on each pair's line is not beaten on a nearby line (the
        reference moved by up to ``window // 2`` frames) by more than ``LOCALISE`` decades of evidence, nor by more
        than ``LOCAL_SPREAD`` null spreads of raw score: evidence carried by the earlier windows does not say which
        frame the query is at, its own window does (a line a few frames off the true one still reads the true one's
        earlier windows, and a revisit faster than the line drifts off it window by window)."""
        scores = self.nearby_scores(queries, refs, source, speed)
        return self._localised(scores, self._evidence(scores))

    def _localised(self, scores: np.ndarray, ev: np.ndarray) -> np.ndarray:
        """``localised`` from ``nearby_scores``' ``(n, window // 2 * 2 + 1)`` and their evidence."""
        mid = self.window // 2
        return (ev[:, mid] >= ev.max(axis=1, initial=0.0) - LOCALISE) & \
            (scores[:, mid] >= scores.max(axis=1, initial=-np.inf) - LOCAL_SPREAD * self.spread)

    def _evidence(self, scores: np.ndarray) -> np.ndarray:
        """The evidence (decades) of window scores of any shape, from the one-window null (``tail``)."""
        return -self.tail.log10_sfs(scores.ravel()).reshape(scores.shape)

    def on_line(self, queries: np.ndarray, refs: np.ndarray, source: Any, speed: float = 1.0) -> np.ndarray:
        """``(n,)`` bool: whether a run's member ``(queries[i], refs[i])`` lies on the run's line: its own window is
        ``localised`` and no line more than one frame off (the confirmation's slack) beats it at all (a frame just
        before a revisit's start has one pair of evidence on the line; a line a few frames off often reads as much)."""
        scores, mid = self.nearby_scores(queries, refs, source, speed), self.window // 2
        ev = self._evidence(scores)
        far = ev[:, np.abs(np.arange(ev.shape[1]) - mid) > 1]  # lines 2 or more frames off (none: a short window)
        return self._localised(scores, ev) & (ev[:, mid] >= far.max(axis=1, initial=0.0))

    def nearby_scores(self, queries: np.ndarray, refs: np.ndarray, source: Any, speed: float = 1.0) -> np.ndarray:
        """``(n, 2 * (window // 2) + 1)``: the query's own window score on each line at ``speed`` through
        ``(queries[i], refs[i] + d)``, ``d = -window // 2 .. window // 2`` (column ``window // 2``: the pair's own
        line; ``-inf`` where the reference would lie before the first frame)."""
        queries, refs = np.asarray(queries, np.int64), np.asarray(refs, np.int64)
        near = np.arange(-(self.window // 2), self.window // 2 + 1, dtype=np.int64)
        qs, rs = np.repeat(queries, len(near)), (refs[:, None] + near[None, :]).ravel()
        ok = rs >= 0
        scores = np.full(len(rs), -np.inf)
        if ok.any():
            scores[ok] = self.score(qs[ok], rs[ok], source, speed)
        return scores.reshape(len(queries), len(near))

    def confidences(self, queries: np.ndarray, refs: np.ndarray, source: Any,
                    accept_at: float = -math.inf) -> np.ndarray:
        """``(n,)`` ``-log10 NFA`` of each pair: the best span's on its best line (``-inf`` where no span agrees, or
        where it reaches ``accept_at`` and the line is not ``localised``: checked only there, as only there it
        decides)."""
        by_span, speed = self._by_speed(queries, refs, source)
        if not by_span.size:
            return np.full(len(by_span), -math.inf)
        best = by_span.max(axis=1)
        check = np.flatnonzero(best >= accept_at)
        queries, refs = np.asarray(queries, np.int64), np.asarray(refs, np.int64)
        for v in np.unique(speed[check]):
            at = check[speed[check] == v]
            best[at[~self.localised(queries[at], refs[at], source, float(v))]] = -math.inf
        return best

    def best_run(self, query_id: int, ref: int, source: Any) -> tuple[float, int, float]:
        """The confidence of ``(query_id, ref)``, the query frames its best span covers (``m * window``; 0: none)
        and its line's speed (read from the rows kept since ``keep_rows`` where the pair is among them: the same
        values, ``_by_speed``'s rows do not depend on the pairs scored beside them)."""
        kept = self._rows.get((int(query_id), int(ref))) if source is self._rows_source else None
        if kept is None:
            by_span, speed = self._by_speed(np.array([query_id], np.int64), np.array([ref], np.int64), source)
            kept = by_span[0], float(speed[0])
        row, speed_kept = kept
        j = int(np.argmax(row))
        return float(row[j]), (j + 1) * self.window if np.isfinite(row[j]) else 0, float(speed_kept)


class Horizon:
    """The oldest keyframe still in the query's own stretch: frames back from the query stay in it while they look
    like the query (cosine >= ``cos``), until ``gap`` frames in a row do not (frames not stored are skipped)."""

    def __init__(self, cos: float, floor: int, gap: int = GAP, max_back: int = MAX_BACK) -> None:
        self.cos, self.floor, self.gap, self.max_back = float(cos), int(floor), int(gap), int(max_back)

    def __call__(self, query_id: int, source: Any) -> int:
        """Keyframes with an id >= the returned one are too recent for ``query_id``."""
        oldest = query_id - self.floor + 1  # the floor: younger frames are excluded anyway
        start, misses, chunk, stop = query_id - 1, 0, 64, max(0, query_id - self.max_back)
        while start >= stop and misses < self.gap:
            refs = np.arange(start, max(stop, start - chunk + 1) - 1, -1, dtype=np.int64)
            sims = source.pairs(np.full(len(refs), query_id, np.int64), refs)
            for ref, sim in zip(refs.tolist(), sims.tolist()):
                if math.isnan(sim):
                    continue
                if sim >= self.cos:
                    misses, oldest = 0, min(oldest, ref)
                elif (misses := misses + 1) >= self.gap:
                    break
            start = int(refs[-1]) - 1
        return oldest


class Stops:
    """How long the camera has stood still at each stored frame: ``length(f)`` = the frames in a row up to ``f``
    whose code is unchanged from the frame before (cosine >= ``cos``; a frame not stored ends a stop). Memoised for
    frames inside a stop, and for the newest ``MOVING_KEPT`` frames found moving (a frame's stop is read by its own
    decision, the next frames' and a replay's several times: Nordland's replays asked 25 000 times), so the memory
    grows with the stops, not the run. The codes of a frame do not change in an instance's life (a refit's new code
    space makes a new ``Decision``)."""

    def __init__(self, cos: float) -> None:
        self.cos = float(cos)
        self._len: dict[int, int] = {}
        self._moving: dict[int, None] = {}  # frames found moving, oldest first (insertion order)

    def lengths(self, frames: np.ndarray, source: Any) -> np.ndarray:
        """``(n,)`` int64: the stop length at each of ``frames`` ``(n,)`` (0: the camera moved onto it)."""
        return np.array([self._length(int(f), source) for f in np.asarray(frames, np.int64).tolist()], np.int64)

    def _length(self, frame: int, source: Any) -> int:
        walk = []
        f = frame
        while f not in self._len and f > 0 and self._still(f, source):
            walk.append(f)
            f -= 1
        n = self._len.get(f, 0)
        for g in reversed(walk):
            n += 1
            self._len[g] = n
        return self._len.get(frame, 0)

    def still(self, frames: np.ndarray, source: Any) -> np.ndarray:
        """``(n,)`` bool: whether each of ``frames`` ``(n,)`` is as like the stored frame before it as ``cos`` (the
        camera stood still onto it; False where either is not stored, and for frame 0)."""
        frames = np.asarray(frames, np.int64).reshape(-1)
        sims = np.full(len(frames), -np.inf)  # compared in float64, as the frame-by-frame check was
        ok = frames >= 1
        if ok.any():
            sims[ok] = np.nan_to_num(source.pairs(frames[ok], frames[ok] - 1).astype(np.float64), nan=-np.inf)
        return sims >= self.cos

    def _still(self, frame: int, source: Any) -> bool:
        if frame in self._moving:
            return False
        still = bool(self.still(np.array([frame], np.int64), source)[0])
        if not still:
            self._moving[frame] = None
            if len(self._moving) > MOVING_KEPT:
                del self._moving[next(iter(self._moving))]
        return still

    def line_admissible(self, query_id: int, refs: np.ndarray, back: int, source: Any) -> np.ndarray:
        """``(m,)`` bool: ``admissible`` at every frame of each pair's line over ``back`` frames (``(query_id - j,
        refs - j)``, ``j < back``; pairs before the first frame skipped): a window whose terms match a stop to a
        shorter one reads one place repeated against a passage, and does not say where the query is."""
        refs = np.asarray(refs, np.int64)
        ok = np.ones(len(refs), bool)
        for j in range(max(int(back), 1)):
            live = ok & (refs - j >= 0)
            if query_id - j >= 0 and live.any():
                ok[live] = self.admissible(query_id - j, refs[live] - j, source)
        return ok

    def admissible(self, query_id: int, refs: np.ndarray, source: Any) -> np.ndarray:
        """``(m,)`` bool: whether each of ``refs`` ``(m,)`` may be the query's loop (a moving query: all; a still one:
        where the reference stood still at least as long as the query has)."""
        refs = np.asarray(refs, np.int64)
        stop = self._length(int(query_id), source)
        if stop == 0:
            return np.ones(len(refs), bool)
        return self.lengths(refs, source) >= stop


class CodeTerms(NamedTuple):
    """What a frame's decision reads from the codes alone (``Decision.code_terms``), for its ``m`` candidates."""

    oldest: int | None  #: the horizon: keyframes from this id on are too recent (None: no horizon)
    allowed: np.ndarray | None  #: ``(m,)`` bool, the pair's own line admissible at a stop (None: no stops)
    allowed_w: np.ndarray | None  #: ``(m,)`` bool, the windows' line admissible at a stop (None: no windows)
    windows: np.ndarray | None  #: ``(m,)`` the score path's fused windows' confidence (None: not windowed)


class Decision:
    """The streaming decision of one run (see the module doc).

    Args:
        pair_tail: the hard-negative inlier tail (``TailModel``); None where verification is off (the score path:
            the calibrated temporal-score confidence decides, and only the "too recent" rule is added here).
        fused_tail: the tail measured on hard-negative sequences of ``E`` (``MeasuredTail``, or a fitted
            ``TailModel`` for a calibration made by hand or before; in decades).
        tests: hypotheses the run tests (the NFA's multiplier).
        accept_at: the confidence a loop needs.
        single: True where one pair may decide alone (geometry separates on this sequence).
        horizon: the "too recent" rule, or None (the frame floor only).
        floor: the fewest inliers that count as evidence (a 7-point model always fits 7).
        span: frames fused.
        tol: offset tolerance.
        min_support: frames with evidence a loop needs when not single.
        spans: the score path's fused windows (``ScoreSpans``), or None (the ``fallback`` confidences decide).
        stops: the "a stop is matched to a stop" rule (``Stops``), or None (not applied).
        speeds: keyframes the map advances per query frame along a run's line (``calibration.speeds``): a run is
            fused on the line of one of them, each counted in ``tests`` (on the inlier path).
        both: on the inlier path, the score path's fused windows (``spans``) decide beside it: a candidate's
            confidence is the larger of the two paths', each path's promise kept on its own budget
            (``expected_false_loops / 2`` each; ``Calibration.decision`` sets it where the score path's nulls were
            measured out of sample, a stream's fit). Where a frame's local features do not verify its revisit
            (a night frame with keypoints of noise), its code and its sequence still decide.
    """

    def __init__(self, pair_tail: TailModel | EmpiricalTail | None, fused_tail: TailModel | MeasuredTail, tests: float,
                 accept_at: float, single: bool,
                 horizon: Horizon | None = None, floor: float = 0.0, span: int = SPAN, tol: int = TOL,
                 min_support: int = 2, spans: ScoreSpans | None = None, stops: Stops | None = None,
                 speeds: tuple[float, ...] = (1.0,), both: bool = False) -> None:
        self.speeds = tuple(float(v) for v in speeds) or (1.0,)
        self.both = bool(both) and pair_tail is not None and spans is not None
        self.pair_tail, self.fused_tail, self.floor = pair_tail, fused_tail, float(floor)
        self.tests = float(tests) * (len(self.speeds) if pair_tail is not None else 1)  # a run tested on each line
        self.stops = stops
        self.accept_at, self.single, self.horizon, self.spans = accept_at, single, horizon, spans
        self.span, self.tol, self.min_support = span, tol, min_support
        self._recent: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=max(self.reach - 1, 1))
        # (frame, its loop's keyframe, confidence, the keyframe of the arrival whose loop it carries): stop_carry
        self._last_loop: tuple[int, int, float, int] | None = None
        self._offered: tuple[int, np.ndarray] | None = None  # (frame, the keyframes stop_carry offered it)

    @property
    def reach(self) -> int:
        """Frames one accepted run covers at most, the query's included: ``span`` frames on the inlier path,
        ``span`` windows of ``spans.window`` frames on the score path, and where it decides beside the inlier path
        (``both``; what ``Confirmations`` keeps)."""
        return self.span * self.spans.window if self._windowed else self.span

    @property
    def _windowed(self) -> bool:
        """Whether the score path's fused windows decide (alone, or beside the inlier path: ``both``)."""
        return self.spans is not None and (self.pair_tail is None or self.both)

    @property
    def confirms(self) -> bool:
        """Whether an accepted run certifies its earlier frames (``Confirmations``): where a run is fused (verified
        frames, or the score path's windows)."""
        return self.pair_tail is not None or self.spans is not None

    def evidence(self, inliers: float) -> float:
        """Pair evidence ``e`` of an inlier count (0 under the floor or when the check did not run)."""
        if self.pair_tail is None or inliers < max(self.floor, 0):
            return 0.0
        return self.pair_tail.evidence(inliers)

    def fused_log10_sf(self, decades: float, frames: int | None = None) -> float:
        """``log10 P_E(E >= decades)`` of the evidence summed over ``frames`` consecutive frames (default ``span``):
        the heavier of the Gamma(frames) and the measured sequence tails."""
        return fused_log10_sf(self.span if frames is None else frames, decades, self.fused_tail)

    def support(self, query_id: int, ref: int, speed: float = 1.0) -> list[tuple[int, float]]:
        """Evidence of the earlier fused frames for the hypothesis ``(query_id, ref)`` on the line of ``speed``
        (frame ``q`` back ``d`` expects keyframe ``ref - speed * d``, ``tol`` frames either side): ``(frames back,
        decades)`` per frame with evidence beyond the choice among its consistent candidates."""
        out, choice = [], math.log10(2 * self.tol + 1)
        for q, refs, ev in reversed(self._recent):  # newest first (the score path's windows may keep more frames)
            if query_id - q >= self.span:
                break
            if not len(refs):
                continue
            ok = np.abs(refs - (ref - speed * (query_id - q))) <= self.tol
            if ok.any() and ev[ok].max() > choice:
                out.append((query_id - q, float(ev[ok].max()) - choice))
        return out

    def _best_line(self, query_id: int, ref: int, e0: float) -> tuple[float, int, float]:
        """``(confidence, run length, speed)`` of the best run of ``(query_id, ref)`` among the lines of
        ``speeds`` (``best_run`` on each line's ``support``; ``tests`` counts every line)."""
        best = (-math.inf, 0, self.speeds[0])
        for speed in self.speeds:
            value, m = self.best_run(e0, self.support(query_id, ref, speed))
            if value > best[0]:
                best = (value, m, speed)
        return best

    def fused(self, e0: float, more: list[tuple[int, float]]) -> float:
        """``-log10 NFA`` of the query's evidence ``e0`` fused with ``more`` (``support``): the best run of ``m``
        consecutive frames ending at the query (``m`` from ``min_support`` to ``span``), its evidence under a
        Gamma(m) null (every frame of the run counted, with or without support) or the measured sequence tail,
        whichever is heavier; ``-inf`` where fewer than ``min_support`` frames carry evidence. The run's ``tests``
        count every ``m`` (the calibration multiplies them)."""
        return self.best_run(e0, more)[0]

    def best_run(self, e0: float, more: list[tuple[int, float]]) -> tuple[float, int]:
        """``fused``'s confidence and the length ``m`` of the run that gives it (0 where no run qualifies)."""
        best, best_m, base = -math.inf, 0, -math.log10(self.tests)
        if 1 + len(more) < self.min_support:
            return best, best_m
        for m in range(max(self.min_support, 1), self.span + 1):
            used = [v for d, v in more if d < m]
            if 1 + len(used) >= self.min_support:
                value = base - self.fused_log10_sf(e0 + sum(used), m)
                if value > best:
                    best, best_m = value, m
        return best, best_m

    def run_members(self, query_id: int, ref: int, inliers: float, source: Any = None) -> list[tuple[int, int]]:
        """The earlier frames of the accepted run of ``(query_id, ref)`` (``inliers``: the pair's counted inliers):
        ``(q', r')`` for each frame ``q'`` of the best run (``best_run``) with evidence on its offset, ``r'`` its most
        evident consistent keyframe; empty where the run alone does not reach ``accept_at`` (a pair accepted alone,
        ``single``, certifies no other frame); on the score path the windows' (``window_members``). Call before
        ``commit(query_id, ...)``."""
        if self.pair_tail is None:
            return self.window_members(query_id, ref, source)
        e0 = self.evidence(inliers)
        if e0 <= 0:
            return []
        value, m, speed = self._best_line(query_id, ref, e0)
        if value < self.accept_at:
            return []
        out, choice = [], math.log10(2 * self.tol + 1)
        for q, refs, ev in self._recent:
            if not 0 < query_id - q < m or not len(refs):
                continue
            ok = np.flatnonzero(np.abs(refs - (ref - speed * (query_id - q))) <= self.tol)
            if len(ok) and ev[ok].max() > choice:
                out.append((int(q), int(refs[ok[np.argmax(ev[ok])]])))
        return out

    def window_members(self, query_id: int, ref: int, source: Any) -> list[tuple[int, int]]:
        """The score path's ``run_members``: the frames of the accepted span (``ScoreSpans.best_run``: ``m`` windows,
        ``m * window`` query frames on the line through ``(query_id, ref)`` at its speed ``v``: frame ``q`` expects
        keyframe ``ref - v (query_id - q)``) whose own window is localised on it, each with its keyframe on that line
        (one frame off at most); empty where the run does not reach ``accept_at`` or the score path does not fuse
        (``source``: the code store the windows are scored on)."""
        if not self._windowed or source is None:
            return []
        value, frames, speed = self.spans.best_run(query_id, ref, source)
        if value < self.accept_at:
            return []
        out, expected = [], []
        for q, refs, _ in self._recent:
            if not 0 < query_id - q < frames or not len(refs):
                continue
            at = int(round(ref - speed * (query_id - q)))
            off = np.abs(refs - at)
            if off.min() <= 1:
                out.append((int(q), int(refs[int(np.argmin(off))])))
                expected.append(at)
        if not out:
            return out
        # a member whose own window a line nearby beats does not lie on the run: the frame just before a revisit's
        # start reads only its own pair on the run's line (KITTI 90's frame 99 on frame 0, the revisit from 100 on)
        qs = np.array([q for q, _ in out], np.int64)
        return [m for m, ok in zip(out, self.spans.on_line(qs, np.array(expected, np.int64), source, speed)) if ok]

    def code_terms(self, query_id: int, refs: np.ndarray, source: Any, windows: bool = True) -> "CodeTerms":
        """What ``confidences`` reads from the codes alone for candidates ``refs`` ``(m,)`` of ``query_id`` (the
        horizon, the stops' admissible lines, the score path's windows): computable before the candidates are
        verified, the same values after (the detector computes them while the worker extracts the query's local
        features). ``windows`` False: beside the inlier path (``both``), the windows are left to ``confidences``,
        which scores them only where the inlier path does not decide (the same confidences: where a verified run
        reaches ``accept_at`` the windows are not read)."""
        return self.code_terms_many(np.array([query_id], np.int64), [refs], source, windows)[0]

    def code_terms_many(self, query_ids: np.ndarray, refs: list[np.ndarray], source: Any,
                        windows: bool = True) -> list["CodeTerms"]:
        """``code_terms`` of frames ``query_ids`` ``(n,)``, each with its candidates ``refs[i]`` (a replay's frames):
        the score path's windows of many frames scored together, ``PAIR_CHUNK // span`` pairs a call (the same
        values as frame by frame: every pair's windows are scored on their own)."""
        refs = [np.asarray(r, np.int64).reshape(-1) for r in refs]
        scored = None
        if self._windowed:
            self.spans.keep_rows(source)
        if self._windowed and (windows or self.pair_tail is None):
            qs = np.repeat(np.asarray(query_ids, np.int64), [len(r) for r in refs])
            scored = self._window_confidences(qs, np.concatenate(refs) if refs else np.zeros(0, np.int64), source)
        out, lo = [], 0
        for query_id, r in zip(np.asarray(query_ids).tolist(), refs):
            hi = lo + len(r)
            out.append(CodeTerms(*self._stop_terms(query_id, r, source),
                                 scored[lo:hi] if scored is not None and len(r) else None))
            lo = hi
        return out

    def _window_confidences(self, queries: np.ndarray, refs: np.ndarray, source: Any) -> np.ndarray:
        """``(n,)`` the score path's fused windows' confidence of each pair (``ScoreSpans.confidences``),
        ``PAIR_CHUNK // span`` pairs a call."""
        step = max(1, PAIR_CHUNK // max(self.spans.span, 1))
        return np.concatenate([np.zeros(0)] + [
            self.spans.confidences(queries[lo:lo + step], refs[lo:lo + step], source, self.accept_at)
            for lo in range(0, len(refs), step)])

    def _stop_terms(self, query_id: int, refs: np.ndarray, source: Any
                    ) -> tuple[int | None, np.ndarray | None, np.ndarray | None]:
        """``code_terms``' horizon and the stops' admissible lines (the pair's own, the windows')."""
        oldest = self.horizon(query_id, source) if self.horizon is not None and len(refs) else None
        # the score path's lines: the query's frame and the one before on each (a query that has just left a stop
        # reads that stop in its window: matched only where the reference's stop, one frame back, was as long)
        stops = self.stops is not None and len(refs)
        allowed = self.stops.line_admissible(query_id, refs, 1, source) \
            if stops and (self.pair_tail is not None or self.spans is None) else None
        allowed_w = self.stops.line_admissible(query_id, refs, 2, source) if stops and self._windowed else None
        return oldest, allowed, allowed_w

    def confidences(self, query_id: int, refs: np.ndarray, inliers: np.ndarray, source: Any,
                    fallback: np.ndarray | None = None, terms: "CodeTerms | None" = None) -> np.ndarray:
        """``-log10 NFA`` of each candidate ``(query_id, refs[i])`` with ``inliers[i]`` (-1: not verified);
        ``-inf`` where it has no evidence of its own, is too recent, or is a still query's keyframe where the
        reference did not stand still as long (``stops``); ``UNSUPPORTED`` where it has evidence of its own but no
        run of frames reaches ``min_support`` yet. Score path (no ``pair_tail``): the fused
        windows' confidence (``spans``), else ``fallback`` (the calibrated temporal-score confidences, ``(m,)``),
        where the keyframe is not too recent. ``terms``: ``code_terms`` of the same candidates, when computed
        before (the score path's windows left out of them, ``windows=False``, are scored here where they are read:
        beside the inlier path, only where no verified run reaches ``accept_at``)."""
        out = np.full(len(refs), -math.inf)
        base = -math.log10(self.tests)
        oldest, allowed, allowed_w, windows = terms if terms is not None else self.code_terms(query_id, refs, source)
        if self.pair_tail is None and windows is None:
            windows, allowed_w = fallback, allowed  # the calibrated temporal-score confidences: the pair's own stop
        refs = np.asarray(refs, np.int64)
        recent = refs >= oldest if oldest is not None else np.zeros(len(refs), bool)
        for i, (ref, inl) in enumerate(zip(refs.tolist(), np.asarray(inliers).tolist())):
            if recent[i] or self.pair_tail is None or (allowed is not None and not allowed[i]):
                continue
            e0 = self.evidence(inl)
            if e0 <= 0:
                continue
            best = self._best_line(query_id, ref, e0)[0]
            if self.single:
                best = max(best, base - self.pair_tail.log10_sf(inl))
            out[i] = max(best, UNSUPPORTED)  # evidence of its own: a later run may certify it (``Confirmations``)
        # beside the inlier path, the windows decide a frame the inlier path does not: where geometry accepts one of
        # its candidates, it says which (KITTI 90's narrower-lens revisit, its last frame 199: its window line through
        # 100, the joint of the two passes, read 2.30 unverified where keyframe 99 was verified, 64 inliers, 1.74)
        if self.pair_tail is not None and (out >= self.accept_at).any():
            return out
        if windows is None and self._windowed:  # left to here (``code_terms(windows=False)``): needed now
            windows = self._window_confidences(np.full(len(refs), query_id, np.int64), refs, source)
        by_windows = np.full(len(refs), -math.inf)
        if windows is not None:
            take = ~recent if allowed_w is None else ~recent & np.asarray(allowed_w, bool)
            by_windows[take] = np.asarray(windows, np.float64)[take]
        return by_windows if self.pair_tail is None else np.maximum(out, by_windows)

    def fresh(self) -> "Decision":
        """The same decision with no frame recorded yet (a replay of a run from its start)."""
        out = copy.copy(self)
        out._recent = deque(maxlen=self._recent.maxlen)
        out._last_loop = out._offered = None
        return out

    def stop_carry(self, query_id: int, refs: np.ndarray, source: Any) -> tuple[np.ndarray, float]:
        """A stop is one place: where the frame before was a loop and the camera has stood still since (``Stops``),
        this frame is that place again, matched to a stop: which of ``refs`` ``(m,)`` is the candidate nearest after
        the frame before's keyframe (the query has not moved) in the reference's own stop (every frame from the
        arrival's keyframe to the candidate one where the reference camera stood still, but for the first
        ``STOP_EDGE``, once per stop), and the confidence the arrival's loop had: the same loop, carried, claiming
        nothing new. A query still where the reference moved on carries nothing.

        Returns:
            ``(m,)`` bool and the carried confidence (all False where nothing is carried).
        """
        refs = np.asarray(refs, np.int64)
        last = self._last_loop
        if self.stops is None or last is None or last[0] != query_id - 1 or not len(refs) or \
                self.stops.lengths(np.array([query_id], np.int64), source)[0] == 0:
            return np.zeros(len(refs), bool), 0.0
        after = refs - last[1]
        inside = (after >= 1) & (self.stops.lengths(refs, source) >= refs - last[3] - STOP_EDGE)
        if inside.any():  # the query has not moved: the reference position nearest the frame before's
            inside &= after == after[inside].min()
        self._offered = (int(query_id), refs[inside])
        return inside, last[2]

    def carry_to(self, query_id: int) -> np.ndarray:
        """``(0,)`` or ``(1,)``: the keyframe ``stop_carry`` would carry the frame before's loop to first (the one after
        its keyframe), kept among the frame's hypotheses whatever its rank; empty where the frame before was no loop."""
        last = self._last_loop
        return np.array([last[1] + 1] if last is not None and last[0] == query_id - 1 else [], np.int64)

    def note_loop(self, query_id: int, ref: int | None, confidence: float = 0.0) -> None:
        """Records the decision of frame ``query_id`` (its loop's keyframe, or None) for ``stop_carry``: a loop to
        the keyframe ``stop_carry`` offered it carries the same arrival, any other is an arrival of its own."""
        offered, last = self._offered, self._last_loop
        carried = offered is not None and last is not None and offered[0] == query_id and ref in offered[1].tolist()
        self._last_loop = None if ref is None else (int(query_id), int(ref), float(confidence),
                                                    last[3] if carried else int(ref))
        self._offered = None

    def commit(self, query_id: int, refs: np.ndarray, inliers: np.ndarray) -> None:
        """Records a processed frame's verified candidates (a resumed run replays its stored ones here)."""
        refs = np.asarray(refs, np.int64)
        inl = np.asarray(inliers, np.float64)
        ev = np.array([self.evidence(x) for x in inl.tolist()], np.float64)
        self._recent.append((int(query_id), refs, ev))


class Confirmations:
    """Delayed confirmations (issue 27): a run of ``m`` consecutive verified frames (or score-path windows) on one
    offset, accepted at frame ``t``, certifies its earlier members too. This keeps the last ``span - 1`` frames'
    admissible candidates (those whose confidence was not vetoed: too recent, a stop, no evidence of their own) and
    whether each frame is a loop already, and gives the members of an accepted run that are not
    (``Decision.run_members``), once each.

    Args:
        span: frames a run covers at most (``Decision.reach``).
    """

    VETO = -1e9  #: the confidence a vetoed candidate is stored with (``LoopDetector``: ``max(value, -1e9)``)

    def __init__(self, span: int = SPAN) -> None:
        self._frames: deque[tuple[int, dict[int, Any], list[bool]]] = deque(maxlen=max(span - 1, 1))

    def add(self, query_id: int, candidates: dict[int, tuple[float, Any]], looped: bool) -> None:
        """Records a decided frame: ``candidates`` ``{ref: (confidence, payload)}`` (the payload is returned with a
        confirmation: a ``Candidate``, a stored row), ``looped`` whether the frame is a loop."""
        kept = {r: p for r, (c, p) in candidates.items() if c > self.VETO}
        self._frames.append((int(query_id), kept, [bool(looped)]))

    def confirm(self, decision: Decision, query_id: int, ref: int, inliers: float,
                source: Any = None) -> list[tuple[int, Any]]:
        """``[(q', payload)]``: the members of the run of ``(query_id, ref)``, accepted now, that were not loops; each
        marked a loop (reported once); ``source``: the code store (the score path's windows). Call before
        ``decision.commit(query_id, ...)``."""
        pending = [(q, kept, looped) for q, kept, looped in self._frames if not looped[0]]
        if not pending:  # every frame the run could certify is a loop already: nothing to read
            return []
        verified = dict(decision.run_members(query_id, ref, inliers, source)) if decision.pair_tail is not None \
            else {}
        # the score path's members only where a verified one does not name the frame (a run of loops: none)
        windows = dict(decision.window_members(query_id, ref, source)) if any(q not in verified for q, _, _ in
                                                                              pending) else {}
        out = []
        for q, kept, looped in pending:
            r, near = (verified[q], (0,)) if q in verified else (windows.get(q), (0, -1, 1))  # the score path's line:
            pick = None if r is None else next((r + d for d in near if r + d in kept), None)  # one frame off at most
            if pick is not None:
                looped[0] = True
                out.append((q, kept[pick]))
        return out
