"""The global pose graph of the fleet, in gtsam: one ``Similarity3`` node per (robot, keyframe), odometry edges between
a robot's consecutive keyframes, an edge for every accepted loop or overlap, re-optimised on demand.

Conventions (``cae_lcd.fleet.sim3.Sim3``, ``x -> s R x + t``):

- A robot's **local pose** of a keyframe is its camera-to-map transform in the robot's own map (KITTI's 3x4 or a 4x4;
  a rigid pose, or a similarity whose scale is kept).
- A **node** holds the keyframe's camera-to-global similarity: ``node = S_robot o local_pose`` where ``S_robot`` maps
  the robot's map into the global frame (``s`` is the global units per local unit). The anchor (the first
  robot added, unless ``set_anchor`` names one: the fleet service stores its choice) has its first keyframe carry a
  tight prior at its local pose, so its map frame is the global frame.
- An **edge** ``a -> b`` measures ``node_a^-1 o node_b``: keyframe b's camera frame expressed in keyframe a's (the
  similarity that maps b-camera points to a-camera points, as ``ransac_sim3`` estimates it from 3D-3D matches).
  Odometry edges are derived from consecutive local poses (``local_a^-1 o local_b``, scale 1 for rigid poses).

gtsam (4.3) offers ``Similarity3``, ``BetweenFactorSimilarity3``, ``PriorFactorSimilarity3`` and
``Values.atSimilarity3`` in Python. gtsam's ``Similarity3(R, t, s)`` maps ``x -> s (R x + t)``: the conversion
below stores ``t / s``. Its tangent vector is ``[rotation (3), translation (3), log scale (1)]``.

Robots that no overlap edge connects to the anchor are left out of the optimisation (their frame is unknown): the
result has no pose and no transform for them.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np

from cae_lcd.core.conf import Choice, ConfigError, Float, Int, configure

from .consistency import PairLink, PairwiseConsistency
from .sim3 import Sim3

__all__ = ["Node", "Edge", "PoseGraph", "GraphResult", "to_gtsam", "from_gtsam", "mean_sim3", "EDGE_KINDS"]

log = logging.getLogger(__name__)

EDGE_KINDS = ("odometry", "loop", "overlap")  #: odometry within a robot, loop within a robot, overlap across robots


@dataclass(frozen=True, order=True)
class Node:
    """One keyframe of one robot."""

    robot: str
    keyframe: int


@dataclass(frozen=True)
class Edge:
    """A relative measurement ``node_a^-1 o node_b`` (see the module doc)."""

    kind: str  #: one of ``EDGE_KINDS``
    a: Node
    b: Node
    relative: Sim3


@dataclass
class GraphResult:
    """What ``PoseGraph.optimize`` found.

    Attributes:
        poses: node -> camera-to-global similarity (``pose_matrix`` gives the 4x4 rigid pose, ``.s`` the scale).
        transforms: robot -> its map-to-global similarity (only robots connected to the anchor).
        error_before: the graph's total (robust) error at the initial guess.
        error_after: the same after optimisation.
        iterations: Levenberg-Marquardt iterations.
    """

    poses: dict[Node, Sim3] = field(default_factory=dict)
    transforms: dict[str, Sim3] = field(default_factory=dict)
    error_before: float = 0.0
    error_after: float = 0.0
    iterations: int = 0

    def pose_matrix(self, node: Node) -> np.ndarray:
        """``(4, 4)`` rigid camera-to-global pose ``[[R, t], [0, 1]]`` of ``node`` (its scale is ``poses[node].s``)."""
        T = self.poses[node]
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = T.R, T.t
        return M


def to_gtsam(T: Sim3) -> gtsam.Similarity3:
    """``Sim3`` (``x -> s R x + t``) -> ``gtsam.Similarity3`` (``x -> s (R x + t')``, ``t' = t / s``)."""
    return gtsam.Similarity3(gtsam.Rot3(T.R), T.t / T.s, T.s)


def from_gtsam(T: gtsam.Similarity3) -> Sim3:
    """``gtsam.Similarity3`` -> ``Sim3`` (inverse of ``to_gtsam``)."""
    R = T.rotation().matrix()
    U, _, Vt = np.linalg.svd(R)  # re-orthonormalise: gtsam's rotation is orthonormal to ~1e-15 only
    return Sim3(T.scale(), U @ Vt, T.scale() * T.translation())


def _sigma_rules() -> dict[str, Any]:
    return {"rotation": Float(0, lo_open=True), "translation": Float(0, lo_open=True),
            "scale": Float(0, lo_open=True)}


class PoseGraph:
    """Robots' keyframes and the edges between them; ``optimize`` solves for every keyframe's global pose.

    Example:
        >>> g = PoseGraph()
        >>> a0 = g.add_keyframe("A", 0, pose_a0); a1 = g.add_keyframe("A", 1, pose_a1)  # doctest: +SKIP
        >>> b0 = g.add_keyframe("B", 0, pose_b0)  # doctest: +SKIP
        >>> g.add_edge("overlap", a1, b0, sim3_b0_in_a1)  # doctest: +SKIP
        >>> g.optimize().transforms["B"]  # doctest: +SKIP
    """

    default_conf: dict[str, Any] = {
        "odometry": {  # noise of an odometry edge, one standard deviation per tangent component
            "rotation": 0.01,  # radians
            "translation": 0.05,  # units of the earlier keyframe's map
            "scale": 0.001,  # log scale (0.001: 0.1% a keyframe); metric odometry small, monocular drift larger
        },
        "loop": {  # noise of a loop or overlap edge (as estimated from 3D-3D matches)
            "rotation": 0.02,  # radians
            "translation": 0.2,  # units of the edge's first keyframe's map
            "scale": 0.02,  # log scale
        },
        "robust": "huber",  # robust kernel on loop and overlap edges: "huber", "cauchy" or "none"
        "robust_k": 1.345,  # kernel width, in standard deviations of the whitened error
        "prior_sigma": 1e-6,  # the anchor's prior on its first keyframe, every tangent component
        "max_iterations": 100,  # Levenberg-Marquardt iterations at most
        "relative_error_tol": 1e-6,  # stop once an iteration lowers the error by less than this fraction
        "consistency": PairwiseConsistency.default_conf,  # which overlap edges of a robot pair are used (PCM)
    }
    conf_rules: dict[str, Any] = {
        "odometry": _sigma_rules(), "loop": _sigma_rules(), "robust": Choice("huber", "cauchy", "none"),
        "robust_k": Float(0, lo_open=True), "prior_sigma": Float(0, lo_open=True), "max_iterations": Int(1),
        "relative_error_tol": Float(0, 1), "consistency": PairwiseConsistency.conf_rules}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "graph")
        self._consistency = PairwiseConsistency(self.conf["consistency"], self.conf["odometry"])
        self.anchor: str | None = None  #: the robot whose map is the global frame: the first added, or ``set_anchor``
        self._local: dict[Node, Sim3] = {}
        self._last: dict[str, Node] = {}
        self._edges: list[Edge] = []
        self._guess: dict[str, Sim3] = {}

    @property
    def nodes(self) -> list[Node]:
        return list(self._local)

    @property
    def edges(self) -> list[Edge]:
        return list(self._edges)

    def local_pose(self, node: Node) -> Sim3:
        return self._local[node]

    def __contains__(self, node: object) -> bool:
        return node in self._local

    def add_keyframe(self, robot: str, keyframe: int, pose: np.ndarray) -> Node:
        """Adds a keyframe and the odometry edge from the robot's previous one.

        Args:
            robot: robot name.
            keyframe: its keyframe id, larger than the robot's previous one.
            pose: ``(3, 4)`` or ``(4, 4)`` camera-to-map pose in the robot's own map.

        Raises:
            ConfigError: a bad pose, or an id not larger than the robot's last.
        """
        local = Sim3.from_pose(pose)
        node = Node(robot, int(keyframe))
        prev = self._last.get(robot)
        if prev is not None and node.keyframe <= prev.keyframe:
            raise ConfigError(f"robot {robot}: keyframe {keyframe} is not after its last one ({prev.keyframe})")
        self._local[node] = local
        self.anchor = self.anchor or robot  # the first robot added, unless set (``set_anchor``)
        if prev is not None:
            self._edges.append(Edge("odometry", prev, node, self._local[prev].to(local)))
        self._last[robot] = node
        return node

    def add_edge(self, kind: str, a: Node, b: Node, relative: Sim3) -> Edge:
        """Adds a loop (same robot) or overlap (two robots) edge measuring ``node_a^-1 o node_b``.

        Raises:
            ConfigError: an unknown kind or node, or a kind that does not fit the robots.
        """
        if kind not in ("loop", "overlap"):
            raise ConfigError(f"edge kind must be loop or overlap (odometry comes from add_keyframe); got {kind!r}")
        for n in (a, b):
            if n not in self._local:
                raise ConfigError(f"no keyframe {n.keyframe} of robot {n.robot} in the graph")
        if (kind == "loop") != (a.robot == b.robot):
            raise ConfigError(f"a {kind} edge joins {'one robot' if kind == 'loop' else 'two robots'}")
        edge = Edge(kind, a, b, relative)
        self._edges.append(edge)
        return edge

    def copy(self) -> "PoseGraph":
        """A copy that later ``add_keyframe``/``add_edge`` calls on this graph do not change (nodes and edges are
        immutable, so they are shared)."""
        other = PoseGraph.__new__(PoseGraph)
        other.conf, other.anchor, other._consistency = self.conf, self.anchor, self._consistency
        other._local, other._last = dict(self._local), dict(self._last)
        other._edges, other._guess = list(self._edges), dict(self._guess)
        return other

    def without(self, robots: set[str]) -> "PoseGraph":
        """A copy without ``robots``' keyframes and every edge touching them (what the others' maps would be)."""
        other = self.copy()
        other._local = {n: p for n, p in self._local.items() if n.robot not in robots}
        other._last = {r: n for r, n in self._last.items() if r not in robots}
        other._edges = [e for e in self._edges if e.a.robot not in robots and e.b.robot not in robots]
        return other

    def set_anchor(self, robot: str | None) -> None:
        """Makes ``robot``'s map frame the global frame (None: none yet; nothing is then merged); the initial guesses
        of the transforms (expressed in the old frame) are forgotten when it changes."""
        if robot != self.anchor:
            self.anchor, self._guess = robot, {}

    def set_transform(self, robot: str, transform: Sim3) -> None:
        """An initial guess of ``robot``'s map-to-global transform (otherwise derived from the overlap edges)."""
        self._guess[robot] = transform

    def trusted_edges(self) -> list[Edge]:
        """The edges the optimisation uses: odometry and loops, and of each robot pair's overlap edges the largest
        pairwise-consistent set (``cae_lcd.fleet.consistency``)."""
        pairs: dict[tuple[str, str], list[Edge]] = {}
        out = []
        for e in self._edges:
            if e.kind == "overlap":
                pairs.setdefault(tuple(sorted((e.a.robot, e.b.robot))), []).append(e)
            else:
                out.append(e)
        position = self._positions(pairs)
        links, kept = [], {}
        for (first, second), edges in pairs.items():
            oriented = [(e.a, e.relative, e.b) if e.a.robot == first else (e.b, e.relative.inverse(), e.a)
                        for e in edges]
            transforms = [self._local[a].compose(rel).compose(self._local[b].inverse()) for a, rel, b in oriented]
            keep = self._consistency.select(transforms, [self._local[b].t for _, _, b in oriented],
                                            [(position[a], position[b]) for a, _, b in oriented])
            if keep:
                kept[(first, second)] = [edges[i] for i in keep]
                links.append(PairLink(first, second, mean_sim3([transforms[i] for i in keep]),
                                      self._local[oriented[keep[0]][2]].t, len(keep)))
        for link in self._consistency.select_pairs(links):
            out += kept[(link.a, link.b)]
        return out

    def _positions(self, pairs: dict[tuple[str, str], list[Edge]]) -> dict[Node, int]:
        """Each keyframe's position along its robot (odometry steps from its first), for robots in ``pairs``."""
        robots = {r for pair in pairs for r in pair}
        count: dict[str, int] = {}
        out = {}
        for n in self._local:  # insertion order: each robot's keyframes in order
            if n.robot in robots:
                out[n] = count.get(n.robot, 0)
                count[n.robot] = out[n] + 1
        return out

    def initial_transforms(self, edges: list[Edge] | None = None) -> dict[str, Sim3]:
        """Map-to-global transforms of the robots connected to the anchor (breadth first over overlap edges among
        ``edges``; None: the trusted ones)."""
        if self.anchor is None:
            return {}
        edges = self.trusted_edges() if edges is None else edges
        found = {self.anchor: Sim3.identity()}
        todo = deque([self.anchor])
        while todo:
            robot = todo.popleft()
            for e in edges:
                if e.kind != "overlap" or robot not in (e.a.robot, e.b.robot):
                    continue
                near, far, rel = (e.a, e.b, e.relative) if e.a.robot == robot else (e.b, e.a, e.relative.inverse())
                if far.robot in found:
                    continue
                node_far = found[robot].compose(self._local[near]).compose(rel)
                found[far.robot] = self._guess.get(far.robot, node_far.compose(self._local[far].inverse()))
                todo.append(far.robot)
        return found

    def optimize(self) -> GraphResult:
        """Levenberg-Marquardt over the robots connected to the anchor, from the initial transforms.

        Returns:
            ``GraphResult`` (empty for an empty graph).
        """
        edges = self.trusted_edges()
        transforms = self.initial_transforms(edges)
        nodes = [n for n in self._local if n.robot in transforms]
        if not nodes:
            return GraphResult()
        keys = {n: i for i, n in enumerate(nodes)}
        values = gtsam.Values()
        for n, k in keys.items():
            values.insert(k, to_gtsam(transforms[n.robot].compose(self._local[n])))
        graph = self._factors(keys, edges)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(self.conf["max_iterations"])
        params.setRelativeErrorTol(self.conf["relative_error_tol"])
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        solution = optimizer.optimize()
        poses = {n: from_gtsam(solution.atSimilarity3(k)) for n, k in keys.items()}
        result = GraphResult(poses, {}, graph.error(values), graph.error(solution), optimizer.iterations())
        for robot in transforms:
            result.transforms[robot] = mean_sim3([poses[n].compose(self._local[n].inverse())
                                                  for n in nodes if n.robot == robot])
        log.debug("pose graph: %d nodes, %d factors, error %.4g -> %.4g in %d iterations", len(nodes),
                 graph.size(), result.error_before, result.error_after, result.iterations)
        return result

    def _factors(self, keys: dict[Node, int], edges: list[Edge]) -> gtsam.NonlinearFactorGraph:
        """The prior on the anchor's first keyframe and one between-factor per edge of ``edges`` among ``keys``."""
        graph = gtsam.NonlinearFactorGraph()
        first = next(n for n in keys if n.robot == self.anchor)
        prior = gtsam.noiseModel.Isotropic.Sigma(7, self.conf["prior_sigma"])
        graph.add(gtsam.PriorFactorSimilarity3(keys[first], to_gtsam(self._local[first]), prior))
        noise = {"odometry": self._noise("odometry"), "loop": self._noise("loop")}
        noise["overlap"] = noise["loop"]
        for e in edges:
            if e.a in keys and e.b in keys:
                graph.add(gtsam.BetweenFactorSimilarity3(keys[e.a], keys[e.b], to_gtsam(e.relative), noise[e.kind]))
        return graph

    def _noise(self, section: str) -> gtsam.noiseModel.Base:
        """Diagonal noise of the section's sigmas, behind the robust kernel for loop and overlap edges."""
        c = self.conf[section]
        base = gtsam.noiseModel.Diagonal.Sigmas(np.array([c["rotation"]] * 3 + [c["translation"]] * 3 + [c["scale"]]))
        if section == "odometry" or self.conf["robust"] == "none":
            return base
        kernel = {"huber": gtsam.noiseModel.mEstimator.Huber, "cauchy": gtsam.noiseModel.mEstimator.Cauchy}
        return gtsam.noiseModel.Robust.Create(kernel[self.conf["robust"]].Create(self.conf["robust_k"]), base)


def mean_sim3(transforms: list[Sim3]) -> Sim3:
    """The mean of similarities: rotation by projecting the mean matrix onto SO(3), scale geometric, translation
    arithmetic (close transforms, as a robot's per-keyframe map-to-global estimates are).

    Raises:
        ConfigError: an empty list.
    """
    if not transforms:
        raise ConfigError("the mean of no transforms is undefined")
    U, _, Vt = np.linalg.svd(sum(T.R for T in transforms))
    if np.linalg.det(U @ Vt) < 0:
        U[:, 2] *= -1
    s = float(np.exp(np.mean([np.log(T.s) for T in transforms])))
    return Sim3(s, U @ Vt, np.mean([T.t for T in transforms], axis=0))
