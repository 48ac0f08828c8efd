"""Naming the keyframe the query is at (issue 27): an accepted loop's keyframe walked along the map to where the
geometry says the query stands.

A revisit at another speed, or a retrieval whose lines lag, accepts a keyframe that sees the same scene from metres
away: along a road, a frame 10 m back shares much of what the query sees, and the pair verifies (KITTI 90's second
pass at 3x: 13-76 inliers 6-24 m off, against 110-226 at the place). The geometry says which way the place lies:
the scale change of the matched features (``verify.scale_change``: ``s`` octaves, > 0 where the query is nearer
what both frames see) against the map's own step between adjacent keyframes (``m``: > 0 where the map's camera
moves toward what it sees).

- **More than a step away** (``|s| > |m|``, in the direction ``sign(s * m)`` along the map): the walk verifies the
  keyframes that way, one after another, while ``s`` keeps its sign and the pair's inliers have not fallen below the
  most found by more than their noise (``2 sqrt(most)``: past the place; a lagging pair's neighbours hold few
  inliers, 12-20, that rise toward the place), ``max_steps`` at most, and names the keyframe with the most inliers
  among those it saw (the accepted one included). Where it meets a keyframe the query may not match (too recent: at
  another speed the place can lie inside the exclusion window) or the map's newest keyframe, or a pair too weak to
  read its scale change, or runs ``max_steps``, still heading on, the query's place is not found among the keyframes
  it may match: no keyframe is named (the detector refuses the loop). Walking back to the map's first keyframe names
  the best seen (nothing lies before it; a query through a wider lens reads as standing further back: its scale
  change never turns).
- **At its place** (``|s| <= |m| / 2``, nearer the accepted keyframe than the midpoint to its neighbour, and the pair
  holds at least the inliers the keyframe shares with that neighbour): nothing walks.
- **Within a step** otherwise (``|s| <= |m|``): the place is the accepted keyframe or a neighbour, and the scale
  change alone does not say which (a weak pair's reads little, or the wrong way): the climb verifies the neighbour it
  points to, then, unless that one holds fewer inliers beyond their noise, the other, moves to one that holds more,
  and goes on until neither neighbour does: the keyframe named holds the most inliers around it. On a dense map it
  names the accepted keyframe or the next (KITTI 90, keyframes 1.6 m apart: the same loops, one named a keyframe
  nearer; 3 checks more over its 100 loops: most neighbours are candidates whose matches, fewer than the accepted
  pair's inliers, already say they hold fewer); on a sparse one it is the difference between the
  place and a keyframe ahead of it: a revisit at a third of the map's speed (KITTI 90's first pass taking every
  third frame, keyframes 4.7 m apart) named keyframes a step or two ahead, 6-11 m off (18-28 inliers, against
  153-172 at the place), whose scale change (0.12-0.38 octaves) stayed within the map's step
  (``bench.revisit_speed``). A SLAM front end's keyframes are sparse by design.

The map's step is one check per keyframe, cached; where the map's camera did not move toward the scene
(``|m| < MIN_STEP``: a stop, a sideways pan) nothing walks.

The detector supplies the map: ``adjacent(ref, d) -> int | None`` the next keyframe from ``ref`` in direction ``d``
(+1 later, -1 earlier) or None, ``admissible(ref) -> bool`` whether the query may match it, ``features_of(ref) ->
Features`` and ``verify(a, b) -> Verification`` (``a`` the query side).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from typing import Callable

from verify.features import Features
from verify.verifier import MIN_SCALE_INLIERS, Verification, scale_change

__all__ = ["Localiser", "MIN_STEP", "MAX_STEPS"]

MIN_STEP = 0.02  #: octaves: a map step whose scale change is smaller is no motion toward the scene (nothing walks)
MAX_STEPS = 16  #: keyframes one walk verifies at most (a revisit at 3x the map's speed lagged up to 12 keyframes)
STEP_CACHE = 4096  #: map steps remembered (one per keyframe that was a loop's; least recently used dropped)

Adjacent = Callable[[int, int], "int | None"]


class Localiser:
    """Walks an accepted loop's keyframe to the query's place (see the module doc).

    Args:
        verify: ``(query side, keyframe side) -> Verification`` of two frames' features.
        features_of: a keyframe's local features by id.
        max_steps: keyframes one walk verifies at most.
    """

    def __init__(self, verify: Callable[[Features, Features], Verification], features_of: Callable[[int], Features],
                 max_steps: int = MAX_STEPS) -> None:
        self._verify, self._features_of = verify, features_of
        self.max_steps = int(max_steps)
        self._steps: OrderedDict[int, tuple[float, int]] = OrderedDict()

    def map_step(self, ref: int, adjacent: Adjacent) -> float:
        """``m``: the scale change from keyframe ``ref`` to the next one (``verify.scale_change`` of the later
        against the earlier; the one before where none follows), in octaves; NaN where neither exists or their pair
        has too few inliers. Cached per keyframe."""
        return self._step(ref, adjacent)[0]

    def _step(self, ref: int, adjacent: Adjacent) -> tuple[float, int]:
        """``(map_step, the inliers of that pair of keyframes)`` (0 where there is none), cached."""
        if ref in self._steps:
            self._steps.move_to_end(ref)
            return self._steps[ref]
        later, earlier = adjacent(ref, 1), ref
        if later is None:
            later, earlier = ref, adjacent(ref, -1)
        step = (math.nan, 0)
        if earlier is not None:
            a, b = self._features_of(later), self._features_of(earlier)
            check = self._verify(a, b)
            step = (scale_change(a, b, check), max(check.inliers, 0))
        self._steps[ref] = step
        while len(self._steps) > STEP_CACHE:
            self._steps.popitem(last=False)
        return step

    def walk(self, query: Features, ref: int, check: Verification, adjacent: Adjacent,
             admissible: Callable[[int], bool], known: dict[int, Verification] | None = None
             ) -> tuple[int | None, list[tuple[int, Verification]]]:
        """The keyframe the query is at, from the accepted ``ref`` and its ``check``.

        Args:
            query: the query's local features.
            ref: the accepted keyframe.
            check: the query's verification against ``ref``.
            adjacent: the map's next keyframe from one in a direction (module doc).
            admissible: whether the query may match a keyframe.
            known: the query's verifications already made, by keyframe (reused, not repeated).

        Returns:
            The named keyframe (``ref`` where the query is at it or no better one was found; from within a step,
            the one that holds the most inliers around it; None where a walk from more than a step away met a
            keyframe the query may not match, the map's newest end or a pair too weak to read, or ran
            ``max_steps``, still heading on: the query's place is not found among the keyframes it may match) and
            the ``(keyframe, Verification)`` pairs the walk made (empty where it did not walk).
        """
        known = known or {}
        s = scale_change(query, self._features_of(ref), check)
        if math.isnan(s):
            return ref, []
        m, shared = self._step(ref, adjacent)
        if math.isnan(m) or abs(m) < MIN_STEP or (abs(s) <= abs(m) / 2 and check.inliers >= shared):
            return ref, []  # at its place (no motion to read; or nearer than half a step, sharing with the query
            #                 at least what the keyframe shares with its neighbour)
        direction = 1 if s * m > 0 else -1
        if abs(s) <= abs(m):
            return self._climb(query, ref, check, direction, adjacent, admissible, known)
        best, most, at, walked = ref, check.inliers, ref, []
        for _ in range(self.max_steps):
            nxt = adjacent(at, direction)
            if nxt is None and direction < 0:
                return best, walked  # the map's first keyframe: nothing before it to name
            if nxt is None or not admissible(nxt):
                return None, walked  # the place lies among keyframes the query may not match (too recent)
            got = self._check(query, nxt, known)
            walked.append((nxt, got))
            if got.inliers > most:
                best, most = nxt, got.inliers
            if got.inliers < most - 2 * math.sqrt(most):  # fewer beyond the count's noise: past the place
                return best, walked
            s_next = scale_change(query, self._features_of(nxt), got)
            if math.isnan(s_next):
                return None, walked  # too few inliers to read which way: the place is not found
            if s_next * s <= 0:  # at the place: the scale change turned
                return best, walked
            at = nxt
        return None, walked  # still going: the place is further than the walk reaches

    def _climb(self, query: Features, ref: int, check: Verification, first: int, adjacent: Adjacent,
               admissible: Callable[[int], bool], known: dict[int, Verification]
               ) -> tuple[int, list[tuple[int, Verification]]]:
        """``walk`` from within one map step (``|s| <= |m|``): the admissible neighbour in direction ``first`` (the
        way the scale change points) verified, then, unless it holds fewer inliers beyond their noise, the other; the
        keyframe moved to one that holds more, until neither does (or ``max_steps``): the keyframe named holds the
        most inliers around it. A neighbour among ``known`` whose check did not run (the verifier's branch and bound)
        and whose matches are no more than the most found cannot hold more, and is not verified."""
        at, most, walked = ref, check.inliers, []
        seen = {ref}
        for _ in range(self.max_steps):
            step = None
            for d in (first, -first):
                nxt = adjacent(at, d)
                if nxt is None or nxt in seen or not admissible(nxt):
                    continue
                seen.add(nxt)
                bound = known.get(nxt)  # a candidate whose check did not run: its inliers are at most its matches
                if bound is not None and bound.inliers < 0 and bound.matches <= most:
                    fewest = bound.matches  # cannot hold more: not verified
                else:
                    got = self._check(query, nxt, known)
                    walked.append((nxt, got))
                    if got.inliers > most:
                        step, most, first = nxt, got.inliers, d
                        break
                    fewest = got.inliers
                if fewest < most - 2 * math.sqrt(most):  # fewer beyond the count's noise: the other way is no
                    break                                 # nearer either (the scale change pointed here)
            if step is None:
                return at, walked
            at = step
        return at, walked

    def _check(self, query: Features, ref: int, known: dict[int, Verification]) -> Verification:
        """The query's verification against keyframe ``ref``: ``known`` where it was made, else now."""
        got = known.get(ref)
        return got if got is not None and got.inliers >= 0 else self._verify(query, self._features_of(ref))
