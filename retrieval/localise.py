"""Naming the keyframe the query is at (issue 27): an accepted loop's keyframe walked along the map to where the
geometry says the query stands.

A revisit at another speed, or a retrieval whose lines lag, accepts a keyframe that sees the same scene from metres
away: along a road, a frame 10 m back shares much of what the query sees, and the pair verifies (KITTI 90's second
pass at 3x: 13-76 inliers 6-24 m off, against 110-226 at the place). The geometry says which way the place lies:
the scale change of the matched features (``verify.scale_change``: ``s`` octaves, > 0 where the query is nearer
what both frames see) against the map's own step between adjacent keyframes (``m``: > 0 where the map's camera
moves toward what it sees). Where ``|s| > |m|`` the query is more than one keyframe away from the accepted one, in
the direction ``sign(s * m)`` along the map. The walk verifies the keyframes that way, one after another, while
``s`` keeps its sign and the pair's inliers have not fallen below the most found by more than their noise
(``2 sqrt(most)``: past the place; a lagging pair's neighbours hold few inliers, 12-20, that rise toward the place),
``max_steps`` at most, and names the keyframe with the most inliers among those it saw (the accepted one
included). Where the walk meets a keyframe the query may not match (too recent: at another speed the place
can lie inside the exclusion window) or the map's newest keyframe, or a pair too weak to read its scale change, or
runs ``max_steps``, still heading on, the query's place is not found among the keyframes it may match: no keyframe is
named (the detector refuses the loop). Walking back to the map's first keyframe names the best seen (nothing lies
before it; a query through a wider lens reads as standing further back: its scale change never turns). A loop at
its place (``|s| <= |m|``) costs the map's step, one check per keyframe, cached; where the map's camera did not move
toward the scene (``|m| < MIN_STEP``: a stop, a sideways pan) nothing walks.

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
        self._steps: OrderedDict[int, float] = OrderedDict()

    def map_step(self, ref: int, adjacent: Adjacent) -> float:
        """``m``: the scale change from keyframe ``ref`` to the next one (``verify.scale_change`` of the later
        against the earlier; the one before where none follows), in octaves; NaN where neither exists or their pair
        has too few inliers. Cached per keyframe."""
        if ref in self._steps:
            self._steps.move_to_end(ref)
            return self._steps[ref]
        later, earlier = adjacent(ref, 1), ref
        if later is None:
            later, earlier = ref, adjacent(ref, -1)
        step = math.nan
        if earlier is not None:
            a, b = self._features_of(later), self._features_of(earlier)
            step = scale_change(a, b, self._verify(a, b))
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
            The named keyframe (``ref`` where the query is at it or no better one was found; None where the walk
            met a keyframe the query may not match, the map's newest end or a pair too weak to read, or ran
            ``max_steps``, still heading on: the query's place is not found among the keyframes it may match) and
            the ``(keyframe, Verification)`` pairs the walk made (empty where it did not walk).
        """
        known = known or {}
        s = scale_change(query, self._features_of(ref), check)
        if math.isnan(s):
            return ref, []
        m = self.map_step(ref, adjacent)
        if math.isnan(m) or abs(m) < MIN_STEP or abs(s) <= abs(m):
            return ref, []
        direction = 1 if s * m > 0 else -1
        best, most, at, walked = ref, check.inliers, ref, []
        for _ in range(self.max_steps):
            nxt = adjacent(at, direction)
            if nxt is None and direction < 0:
                return best, walked  # the map's first keyframe: nothing before it to name
            if nxt is None or not admissible(nxt):
                return None, walked  # the place lies among keyframes the query may not match (too recent)
            feats, got = self._features_of(nxt), known.get(nxt)
            if got is None or got.inliers < 0:
                got = self._verify(query, feats)
            walked.append((nxt, got))
            if got.inliers > most:
                best, most = nxt, got.inliers
            if got.inliers < most - 2 * math.sqrt(most):  # fewer beyond the count's noise: past the place
                return best, walked
            s_next = scale_change(query, feats, got)
            if math.isnan(s_next):
                return None, walked  # too few inliers to read which way: the place is not found
            if s_next * s <= 0:  # at the place: the scale change turned
                return best, walked
            at = nxt
        return None, walked  # still going: the place is further than the walk reaches
