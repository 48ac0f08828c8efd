"""The fleet server's core without HTTP: robots and tokens, keyframe acknowledgements and the global pose graph, kept in
a ``FleetStore`` and rebuilt from it on start (a server killed with ``kill -9`` continues with every keyframe it
acknowledged).

Not here yet (issue 12, open): place recognition across robots (the keyframe images are decoded and checked, not
stored in the HDF5 keyframe database nor searched), so overlap edges come only through ``add_edge``; the graph is
re-optimised on demand (``poses``), not in a background thread.
"""

from __future__ import annotations

import hashlib
import logging
import re
import secrets
import threading
import time
from typing import Any

import numpy as np

from core.conf import ConfigError, configure

from .graph import GraphResult, Node, PoseGraph
from .sim3 import Sim3
from .store import EdgeRecord, FleetStore, KeyframeAck

__all__ = ["FleetService", "ROBOT_NAME"]

log = logging.getLogger(__name__)

ROBOT_NAME = r"[A-Za-z0-9_-]{1,64}"  #: what a robot's name may be


class FleetService:
    """Robots, keyframes and the pose graph over one store; safe to call from several threads (one lock)."""

    default_conf: dict[str, Any] = {
        "graph": PoseGraph.default_conf,  # the global pose graph (fleet.graph.PoseGraph)
    }
    conf_rules: dict[str, Any] = {"graph": PoseGraph.conf_rules}

    def __init__(self, store: FleetStore, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "fleet")
        self.store = store
        self._lock = threading.Lock()
        self._verified: set[bytes] = set()  # sha256(name, token) of tokens already checked (PBKDF2 is slow)
        self._graph = PoseGraph(self.conf["graph"])
        self._result: GraphResult | None = None
        self._rebuild()

    def _rebuild(self) -> None:
        """The graph from the store: every robot's acknowledged keyframes, then the loop and overlap edges."""
        for robot in self.store.robots():
            for ack in self.store.keyframes(robot):
                self._graph.add_keyframe(robot, ack.keyframe, ack.pose)
        for e in self.store.edges():
            if e.kind != "odometry":
                self._graph.add_edge(e.kind, Node(e.robot_a, e.keyframe_a), Node(e.robot_b, e.keyframe_b), e.relative)
        log.info("fleet state: %d robots, %d keyframes", len(self.store.robots()), len(self._graph.nodes))

    def register(self, name: str) -> str:
        """Registers a robot; returns its new token ``NAME.SECRET`` (shown once, stored hashed).

        Raises:
            ConfigError: a bad or taken name.
        """
        if not isinstance(name, str) or not re.fullmatch(ROBOT_NAME, name):
            raise ConfigError(f"a robot name must match {ROBOT_NAME}; got {name!r}")
        token = f"{name}.{secrets.token_urlsafe(32)}"
        self.store.add_robot(name, token)
        return token

    def authenticate(self, name: str, token: str) -> bool:
        """True when ``token`` is robot ``name``'s (checked against the stored hash once, then remembered)."""
        key = hashlib.sha256(f"{name}\0{token}".encode()).digest()
        if key in self._verified:
            return True
        if self.store.verify_token(name, token):
            self._verified.add(key)
            return True
        return False

    def submit_keyframe(self, robot: str, keyframe: int, timestamp: float, pose: np.ndarray) -> bool:
        """Acknowledges a keyframe (stored with its odometry edge, then added to the graph).

        Returns:
            True when new, False for a retry of a stored keyframe.

        Raises:
            ConfigError: a bad pose, an id not after the robot's last, or a conflicting retry.
        """
        local = Sim3.from_pose(pose)
        with self._lock:
            node = Node(robot, int(keyframe))
            ack = KeyframeAck(robot, node.keyframe, float(timestamp), local.matrix())
            acks = {a.keyframe: a for a in self.store.keyframes(robot)}
            if node.keyframe in acks:
                return self.store.ack_keyframe(ack)  # a retry (False) or a conflict (ConfigError)
            last = acks[max(acks)] if acks else None
            if last is not None and node.keyframe < last.keyframe:
                raise ConfigError(f"robot {robot}: keyframe {keyframe} is not after its last one ({last.keyframe})")
            edges = [] if last is None else [EdgeRecord("odometry", robot, last.keyframe, robot, node.keyframe,
                                                        Sim3.from_pose(last.pose).inverse().compose(local))]
            self.store.ack_keyframe(ack, edges)
            self._graph.add_keyframe(robot, node.keyframe, local.matrix())
            self._result = None
            return True

    def add_edge(self, edge: EdgeRecord) -> None:
        """Stores a loop or overlap edge and adds it to the graph."""
        with self._lock:
            a, b = Node(edge.robot_a, edge.keyframe_a), Node(edge.robot_b, edge.keyframe_b)
            self._graph.add_edge(edge.kind, a, b, edge.relative)  # checks kind and nodes before the store
            self.store.add_edges([edge])
            self._result = None

    def optimize(self) -> GraphResult:
        """The optimised graph (cached until a keyframe or edge arrives); robots' transforms are stored."""
        with self._lock:
            if self._result is None:
                started = time.perf_counter()
                self._result = self._graph.optimize()
                self.store.set_transforms(self._result.transforms)
                log.info("graph optimised in %.3f s", time.perf_counter() - started)
            return self._result

    def poses(self, robot: str) -> list[dict[str, Any]]:
        """``[{"keyframe", "pose" (4x4 rows), "scale"}]`` of the robot's corrected keyframes (empty: not merged)."""
        result = self.optimize()
        return [{"keyframe": n.keyframe, "pose": result.pose_matrix(n).tolist(), "scale": T.s}
                for n, T in sorted(result.poses.items()) if n.robot == robot]
