"""Pairwise consistency of inter-robot edges (PCM, Mangelson et al. 2018), before they can move anyone's map.

Every overlap edge between robots ``a`` and ``b`` implies a map-to-map similarity ``T = L_a o rel o L_b^-1`` (``L``:
the keyframes' local poses, ``rel``: the edge). Two edges are consistent when their ``T`` agree (rotation, log scale,
and where they put both edges' b-keyframes in a's map) within a tolerance that grows, as PCM's Mahalanobis test does,
with the odometry between them: ``n`` odometry steps apart (in both robots) add ``3 sigma sqrt(n)`` of the odometry
noise (``cae_lcd.fleet.graph`` ``odometry`` sigmas), the rotation part times the distance between the keyframes. Of each robot pair's edges, only the largest mutually
consistent set enters the pose graph: an edge made of a wrong match, or of a robot's garbage poses, agrees with
nothing and is left out. Across pairs, the robots' map-to-map transforms must agree around every cycle: pairs are
taken by support (most consistent edges first) and one whose transform contradicts the path already joining its two
robots is left out (``select_pairs``). So a robot that sends garbage corrupts only its own trajectory.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from cae_lcd.core.conf import Bool, Float, Int, configure

from .sim3 import Sim3

__all__ = ["PairwiseConsistency", "PairLink"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PairLink:
    """One robot pair's consistent edges, summarised: ``transform`` maps b's map into a's, ``centre`` is a b-keyframe
    position (``(3,)``, b's map) it was measured at, ``support`` the number of its consistent edges."""

    a: str
    b: str
    transform: Sim3
    centre: np.ndarray
    support: int


class PairwiseConsistency:
    """The largest pairwise-consistent set of one robot pair's edges (greedy maximum clique)."""

    default_conf: dict[str, Any] = {
        "enabled": True,  # False: every edge is used (the robust kernel alone limits a wrong one)
        "max_rotation_deg": 5.0,  # two edges' map-to-map rotations differ by at most this
        "max_log_scale": 0.1,  # two edges' map-to-map scales differ by at most this (|log s1/s2|)
        "max_distance": 5.0,  # the two transforms put either edge's keyframe this close (units of a's map)
        "min_support": 1,  # a pair's consistent set needs this many edges; fewer: none of its edges is used
    }
    conf_rules: dict[str, Any] = {"enabled": Bool(), "max_rotation_deg": Float(0, 180, lo_open=True),
                                  "max_log_scale": Float(0, lo_open=True), "max_distance": Float(0, lo_open=True),
                                  "min_support": Int(1)}

    def __init__(self, conf: dict[str, Any] | None = None, odometry: dict[str, float] | None = None) -> None:
        self.conf = configure(self, conf, "consistency")
        self.odometry = dict(odometry or {"rotation": 0.0, "translation": 0.0, "scale": 0.0})  # sigmas a step

    def consistent(self, T1: Sim3, c1: np.ndarray, T2: Sim3, c2: np.ndarray, steps: int = 0) -> bool:
        """Whether two map-to-map similarities agree, judged at the b-keyframe positions ``c1``, ``c2`` (``(3,)``),
        for edges ``steps`` odometry steps apart."""
        c, o, k = self.conf, self.odometry, 3.0 * np.sqrt(max(steps, 0))
        D = T1.R.T @ T2.R
        angle = np.arccos(np.clip((np.trace(D) - 1) / 2, -1.0, 1.0))
        if angle > np.radians(c["max_rotation_deg"]) + k * o["rotation"] \
                or abs(np.log(T2.s / T1.s)) > c["max_log_scale"] + k * o["scale"]:
            return False
        span = T1.s * np.linalg.norm(np.asarray(c1) - np.asarray(c2))
        gaps = [np.linalg.norm(T1.apply(p) - T2.apply(p)) for p in (c1, c2)]
        return bool(max(gaps) <= c["max_distance"] + k * (o["translation"] + o["rotation"] * span))

    def select(self, transforms: Sequence[Sim3], centres: Sequence[np.ndarray],
               steps: Sequence[tuple[int, int]] | None = None) -> list[int]:
        """Indices of the largest mutually consistent subset of one robot pair's edges; empty when under
        ``min_support``.

        Args:
            transforms: edge i's map-to-map similarity. centres: ``(3,)`` its b-keyframe's position in b's map.
            steps: ``(a position, b position)`` of edge i's keyframes along their robots (odometry steps); None: 0.
        """
        n = len(transforms)
        if not self.conf["enabled"]:
            return list(range(n))
        steps = [(0, 0)] * n if steps is None else steps
        ok = np.eye(n, dtype=bool)
        for i in range(n):
            for j in range(i + 1, n):
                gap = abs(steps[i][0] - steps[j][0]) + abs(steps[i][1] - steps[j][1])
                ok[i, j] = ok[j, i] = self.consistent(transforms[i], centres[i], transforms[j], centres[j], gap)
        chosen: list[int] = []
        for i in sorted(range(n), key=lambda k: (-int(ok[k].sum()), k)):  # most supported first, then earliest
            if all(ok[i, j] for j in chosen):
                chosen.append(i)
        if len(chosen) < self.conf["min_support"]:
            return []
        if len(chosen) < n:
            log.info("%d of %d inter-robot edges inconsistent with the others: left out", n - len(chosen), n)
        return sorted(chosen)

    def select_pairs(self, links: Sequence[PairLink]) -> list[PairLink]:
        """The robot pairs whose transforms agree around every cycle: taken by support (then order), a pair whose
        robots are already joined by the pairs kept is kept only if the path's transform agrees with its own."""
        if not self.conf["enabled"]:
            return list(links)
        root: dict[str, str] = {}
        to_root: dict[str, Sim3] = {}  # robot -> similarity from its map into its component root's map
        kept = []
        for link in sorted(links, key=lambda p: -p.support):
            for r in (link.a, link.b):
                if r not in root:
                    root[r], to_root[r] = r, Sim3.identity()
            if root[link.a] == root[link.b]:
                path = to_root[link.a].inverse().compose(to_root[link.b])  # b's map -> a's map through the kept pairs
                if not self.consistent(link.transform, link.centre, path, link.centre):
                    log.info("robot pair %s-%s left out: its transform contradicts the other pairs'", link.a, link.b)
                    continue
            else:
                joint = to_root[link.a].compose(link.transform).compose(to_root[link.b].inverse())
                old = root[link.b]
                for r in [r for r in root if root[r] == old]:
                    root[r], to_root[r] = root[link.a], joint.compose(to_root[r])
            kept.append(link)
        return kept
