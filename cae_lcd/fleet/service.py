"""The fleet server's core without HTTP: robots and tokens, keyframes, place recognition across robots
(``cae_lcd.fleet.recognition``) and the global pose graph re-optimised in the background (``cae_lcd.fleet.optimizer``), kept in a
``FleetStore`` (SQLite) and the robots' HDF5 keyframe databases, and rebuilt from them on start: a server killed with
``kill -9`` continues with every keyframe it acknowledged (a keyframe is in both before ``submit_keyframe`` returns).
"""

from __future__ import annotations

import hashlib
import logging
import secrets
import threading
from typing import Any

import numpy as np

from cae_lcd.core.checks import check_frame_id, check_intrinsics, check_rigid_pose, check_timestamp
from cae_lcd.core.conf import ConfigError, Float, Int, configure
from cae_lcd.core.errors import ConflictError

from .graph import GraphResult, Node, PoseGraph
from .optimizer import BackgroundOptimizer
from .recognition import FleetRecognizer, Recognition
from .sim3 import Sim3
from .store import ROBOT_NAME, EdgeRecord, FleetStore, KeyframeAck, check_robot_name

__all__ = ["FleetService", "ROBOT_NAME"]

log = logging.getLogger(__name__)


class FleetService:
    """Robots, keyframes, place recognition and the pose graph over one store; safe to call from several threads
    (each robot's keyframes one at a time, different robots' at once when the recognizer allows it:
    ``parallel_robots``; the graph is solved in a worker thread).

    Args:
        store: the robots, tokens, keyframes and edges.
        conf: overrides of ``default_conf``.
        recognizer: place recognition over the robots' keyframes; None: keyframes are only acknowledged (overlaps
            then come through ``add_edge`` alone).
    """

    default_conf: dict[str, Any] = {
        "graph": PoseGraph.default_conf,  # the global pose graph (cae_lcd.fleet.graph.PoseGraph)
        "optimizer": BackgroundOptimizer.default_conf,  # when the graph is solved (cae_lcd.fleet.optimizer)
        "limits": {
            "max_request_mb": 32.0,  # larger request bodies are refused (HTTP 413)
            "max_buffered_mb": 256.0,  # an address's request bodies in memory at once (>= max_request_mb); then 429
            #                            (a fleet behind one NAT or proxy is one address: 64 robots' 2 MB keyframes)
            "max_json_values": 1000,  # bodies holding more JSON values are refused unparsed (HTTP 413; a keyframe: ~40)
            "max_image_pixels": 16_000_000,  # larger images are refused (HTTP 413), from their header
            "keyframes_in_flight": 2,  # a robot's further keyframes sent at once are refused (HTTP 429), not queued
            "body_timeout_s": 60.0,  # a request body not received within this is refused (HTTP 408)
            "header_timeout_s": 10.0,  # a connection whose request headers are not in within this is closed
            "max_connections_per_address": 256,  # an address's further connections are closed at once (a fleet
            #                                      streaming from one machine or NAT holds one or two a robot)
            "auth_failures": 20,  # failed authentications an address may make per window; then HTTP 429
            "auth_window_s": 60.0,  # the window of auth_failures, seconds
            "token_hashes_per_s": 5.0,  # token hashes (PBKDF2, ~0.1 s of CPU each) the server computes a second on
            #                             average, for every address and name together; past it HTTP 429 (a robot
            #                             whose token was verified before needs none)
            "token_hash_burst": 20,  # ... and at once
            "robot_hashes_per_s": 0.5,  # token hashes a second for one robot name (a guessed token of it included)
            "robot_hash_burst": 5,  # ... and at once
        },
    }
    conf_rules: dict[str, Any] = {"graph": PoseGraph.conf_rules, "optimizer": BackgroundOptimizer.conf_rules,
                                  "limits": {"max_request_mb": Float(0, lo_open=True), "max_json_values": Int(64),
                                             "max_buffered_mb": Float(0, lo_open=True),
                                             "max_image_pixels": Int(64), "keyframes_in_flight": Int(1),
                                             "body_timeout_s": Float(0, lo_open=True),
                                             "header_timeout_s": Float(0, lo_open=True),
                                             "max_connections_per_address": Int(1), "auth_failures": Int(1),
                                             "auth_window_s": Float(0, lo_open=True),
                                             "token_hashes_per_s": Float(0, lo_open=True),
                                             "token_hash_burst": Int(1),
                                             "robot_hashes_per_s": Float(0, lo_open=True),
                                             "robot_hash_burst": Int(1)}}

    def __init__(self, store: FleetStore, conf: dict[str, Any] | None = None,
                 recognizer: FleetRecognizer | None = None) -> None:
        self.conf = configure(self, conf, "fleet")
        self.store = store
        self.recognizer = recognizer
        self._lock = threading.Lock()  # the graph
        self._submit = threading.Lock()  # one keyframe at a time through recognition and the store
        self._robot_locks: dict[str, threading.Lock] = {}  # per robot, when the recognizer runs robots in parallel
        self._verified: dict[bytes, str] = {}  # sha256(name, token) -> name of tokens already checked (PBKDF2 is slow)
        self._graph = PoseGraph(self.conf["graph"])
        self.anchor: str | None = None
        self._anchor_merged: str | None = None  # the anchor, once it has an overlap edge (``_settle_anchor``)
        #: robots whose files could not be read at start-up (or since): name -> why; their requests are refused (503)
        self.quarantined: dict[str, str] = dict(getattr(recognizer, "quarantined", {}))
        self._rebuild()
        if recognizer is not None:
            recognizer.resume(self.store.overlaps(), self.store.edges(kind="overlap"))
        self.optimizer = BackgroundOptimizer(self._snapshot, self._publish, self.conf["optimizer"])

    def _snapshot(self) -> PoseGraph:
        with self._lock:
            return self._graph.copy()

    def graph(self) -> PoseGraph:
        """A copy of the pose graph as it is now (later keyframes do not change it)."""
        return self._snapshot()

    def _publish(self, result: GraphResult) -> None:
        self.store.set_transforms(result.transforms)

    def _rebuild(self) -> None:
        """The graph from the store: every robot's acknowledged keyframes, then the loop and overlap edges. A stored
        value that cannot be loaded (a pose or an edge no check would accept today) is reported and skipped: the
        server always starts."""
        skipped = 0
        for robot in self.store.robots():
            for ack in self.store.keyframes(robot):
                try:
                    self._graph.add_keyframe(robot, ack.keyframe, check_rigid_pose(ack.pose))
                except ConfigError as err:
                    skipped += 1
                    log.warning("stored keyframe %d of robot %s skipped: %s", ack.keyframe, robot, err)
        for e in self.store.edges():
            if e.kind == "odometry":
                continue
            try:
                self._graph.add_edge(e.kind, Node(e.robot_a, e.keyframe_a), Node(e.robot_b, e.keyframe_b), e.relative)
            except ConfigError as err:
                skipped += 1
                log.warning("stored %s edge %s %d -> %s %d skipped: %s", e.kind, e.robot_a, e.keyframe_a, e.robot_b,
                            e.keyframe_b, err)
        self._set_anchor(None)
        self._settle_anchor()
        log.info("fleet state: %d robots, %d keyframes (%d stored values skipped)", len(self.store.robots()),
                 len(self._graph.nodes), skipped)

    def _set_anchor(self, robot: str | None) -> None:
        """The global frame is the stored anchor's map: the robot of the first keyframe acknowledged (``robot``;
        another front end's choice when it stored one first) until a map is merged (``_settle_anchor``), or the
        admin's (``set_anchor``). A state of an older version without a stored anchor keeps its old one: the first
        registered robot with keyframes. Call under the graph lock (or before the service runs)."""
        anchor = self.store.anchor()
        if anchor is None:
            present = {n.robot for n in self._graph.nodes}
            candidate = robot or next((r for r in self.store.robots() if r in present), None)
            anchor = None if candidate is None else self.store.set_anchor(candidate)
        self.anchor = anchor  #: the robot whose map frame is the global frame (None: no keyframe yet)
        self._graph.set_anchor(anchor)

    def _settle_anchor(self) -> None:
        """The first robot whose map is merged is the anchor for good: while the anchor has no overlap edge (it is
        alone: no other map is expressed in its frame), the first overlap edge between two other robots makes the one
        of them registered first the anchor (a lone robot that spoke first, a hostile one included, does not become
        the fleet's frame). Once the anchor has an overlap edge, nothing but the admin changes it. Call under the
        graph lock."""
        if self.anchor is None or self._anchor_merged == self.anchor:
            return
        edges = [e for e in self._graph.edges if e.kind == "overlap"]
        if any(self.anchor in (e.a.robot, e.b.robot) for e in edges):
            self._anchor_merged = self.anchor  # for good: no scan of the edges again
            return
        if not edges:
            return
        pair = {edges[0].a.robot, edges[0].b.robot}
        choice = next((r for r in self.store.robots() if r in pair), None)
        if choice is not None:
            log.info("the first merged maps are robots %s: robot %s is the anchor (robot %s was alone)",
                     " and ".join(sorted(pair)), choice, self.anchor)
            self.anchor = self.store.set_anchor(choice, replace=True)
            self._graph.set_anchor(self.anchor)

    def register(self, name: str) -> str:
        """Registers a robot; returns its new token ``NAME.SECRET`` (shown once, stored hashed).

        Raises:
            ConfigError: a bad or taken name.
        """
        check_robot_name(name)
        token = f"{name}.{secrets.token_urlsafe(32)}"
        self.store.add_robot(name, token)
        return token

    def has_robot(self, name: str) -> bool:
        """True when robot ``name`` is registered."""
        return name in self.store.robots()

    def known_token(self, name: str, token: str) -> bool:
        """True when ``token`` was already verified as robot ``name``'s (no hash computed)."""
        return hashlib.sha256(f"{name}\0{token}".encode()).digest() in self._verified

    def authenticate(self, name: str, token: str) -> bool:
        """True when ``token`` is robot ``name``'s (checked against the stored hash once, then remembered)."""
        key = hashlib.sha256(f"{name}\0{token}".encode()).digest()
        if key in self._verified:
            return True
        if self.store.verify_token(name, token):
            self._verified[key] = name
            return True
        return False

    def _forget_tokens(self, robot: str) -> None:
        """Forgets the robot's verified tokens (rotated or retired: the old one must be hashed again, and fail)."""
        for key in [k for k, name in list(self._verified.items()) if name == robot]:
            self._verified.pop(key, None)

    def submit_keyframe(self, robot: str, keyframe: int, timestamp: float, pose: np.ndarray,
                        image: np.ndarray | None = None, K: np.ndarray | None = None,
                        depth: np.ndarray | None = None) -> bool:
        """Acknowledges a keyframe: place recognition on its image (stored in the robot's keyframe database), then
        the keyframe, its odometry edge and any loop or overlap edge it found in the store, then the graph.

        Args:
            robot: a registered robot. keyframe: its id, after the robot's last. timestamp: seconds, finite.
            pose: ``(3, 4)``/``(4, 4)`` camera-to-map pose in the robot's map. image: the keyframe's image, or None
                (no recognition). K: ``(3, 3)`` intrinsics. depth: ``(H, W)`` depth map in map units.

        Returns:
            True when new, False for a retry of a stored keyframe.

        Raises:
            ConfigError, ImageError: a bad value (``cae_lcd.core.checks``: id, timestamp, rigid pose, intrinsics), an id not
                after the robot's last, a timestamp before its last; nothing was stored.
            ConflictError: a retry of a stored keyframe with another timestamp, pose, image or intrinsics; nothing
                changed.
        """
        keyframe, timestamp = check_frame_id(keyframe, "keyframe"), check_timestamp(timestamp)
        local = Sim3.from_pose(check_rigid_pose(pose))
        K = None if K is None else check_intrinsics(K)
        with self._submit_lock(robot):
            ack = KeyframeAck(robot, keyframe, timestamp, local.matrix())
            # the store, not this process: replicas share it (one row each, not the robot's every keyframe)
            if self.store.keyframe(robot, keyframe) is not None:  # a retry (False) or a conflict (ConflictError)
                self._check_retry(robot, keyframe, image, K)
                return self.store.ack_keyframe(ack)
            last = self.store.last_keyframe(robot)
            if last is not None and keyframe < last.keyframe:
                raise ConfigError(f"robot {robot}: keyframe {keyframe} is not after its last one ({last.keyframe})")
            if last is not None and timestamp < last.timestamp:
                raise ConfigError(f"robot {robot}: timestamp {timestamp!r} is before its last keyframe's "
                                  f"({last.timestamp!r})")
            found = self._recognize(ack, image, K, depth)
            edges = [] if last is None else [EdgeRecord("odometry", robot, last.keyframe, robot, ack.keyframe,
                                                        Sim3.from_pose(last.pose).to(local))]
            self.store.ack_keyframe(ack, edges + found.edges)
            if self.recognizer is not None:
                self.recognizer.committed(robot)  # stored: other robots may match it now (Ray workers share it)
            if found.overlaps:  # the store is shared: another replica's worker may have accepted the pair already
                known = {frozenset((o.robot_a, o.robot_b)) for o in self.store.overlaps()}
                for overlap in found.overlaps:
                    if frozenset((overlap.robot_a, overlap.robot_b)) not in known:
                        self.store.add_overlap(overlap)
            with self._lock:
                self._graph.add_keyframe(robot, ack.keyframe, ack.pose)
                self._catch_up(found.edges)
                if self.anchor is None:  # the fleet's first keyframe: its robot's map is the global frame, for good
                    self._set_anchor(robot)
                self._graph.set_anchor(self.anchor)  # not the graph's own choice (its first robot added)
                for e in found.edges:
                    self._graph.add_edge(e.kind, Node(e.robot_a, e.keyframe_a), Node(e.robot_b, e.keyframe_b),
                                         e.relative)
                if any(e.kind == "overlap" for e in found.edges):
                    self._settle_anchor()
            self.optimizer.changed()
            return True

    def _check_retry(self, robot: str, keyframe: int, image: np.ndarray | None, K: np.ndarray | None) -> None:
        """Refuses (``ConflictError``) a retry of a stored keyframe with another image or other intrinsics than the
        robot's (both may be left out of a retry); changes nothing."""
        if self.recognizer is None:
            return
        try:
            self.recognizer.check(robot, K)
        except ConfigError:
            raise ConflictError(f"robot {robot!r} sent keyframe {keyframe} before, with other intrinsics") from None
        if image is not None:
            self.recognizer.check_retry(robot, keyframe, image)

    def _catch_up(self, edges: list[EdgeRecord]) -> None:
        """Adds to the graph the keyframes that ``edges`` join and another front end on the same store acknowledged
        (a replica: ``cae_lcd.fleet.stores``), read from the store; call under the graph lock."""
        known = self._graph.nodes
        last: dict[str, int] = {}
        for n in known:
            last[n.robot] = max(last.get(n.robot, -1), n.keyframe)
        for robot in {r for e in edges for r in (e.robot_a, e.robot_b)}:
            if any(Node(r, k) not in known for e in edges for r, k in ((e.robot_a, e.keyframe_a),
                                                                      (e.robot_b, e.keyframe_b)) if r == robot):
                for ack in self.store.keyframes(robot, after=last.get(robot, -1)):
                    self._graph.add_keyframe(robot, ack.keyframe, ack.pose)

    def _submit_lock(self, robot: str) -> threading.Lock:
        """The lock a robot's keyframe is processed under: one for all robots, or one per robot when the recognizer
        processes robots in parallel (``cae_lcd.fleet.workers.RayRecognizer``)."""
        if self.recognizer is None or not self.recognizer.parallel_robots:
            return self._submit
        with self._submit:
            return self._robot_locks.setdefault(robot, threading.Lock())

    def _recognize(self, ack: KeyframeAck, image: np.ndarray | None, K: np.ndarray | None,
                   depth: np.ndarray | None) -> Recognition:
        """Place recognition of a new keyframe (nothing without an image or a recognizer, or when the robot's
        keyframe database already holds it: a server killed between the two writes)."""
        if self.recognizer is None or image is None:
            return Recognition()
        if self.recognizer.has(ack.robot, ack.keyframe):
            self.recognizer.check(ack.robot, K)
            return Recognition()
        return self.recognizer.process(ack.robot, ack.keyframe, ack.timestamp, ack.pose, image, K, depth)

    def add_edge(self, edge: EdgeRecord) -> None:
        """Stores a loop or overlap edge and adds it to the graph."""
        with self._lock:
            a, b = Node(edge.robot_a, edge.keyframe_a), Node(edge.robot_b, edge.keyframe_b)
            self._graph.add_edge(edge.kind, a, b, edge.relative)  # checks kind and nodes before the store
            self.store.add_edges([edge])
            if edge.kind == "overlap":
                self._settle_anchor()
        self.optimizer.changed()

    def optimize(self, wait: bool = True, timeout: float = 30.0) -> GraphResult:
        """The optimised graph: one that includes every change so far (``wait``, up to ``timeout`` s), else the
        latest finished one."""
        return self.optimizer.wait(timeout) if wait else self.optimizer.latest()

    def poses(self, robot: str, wait: bool = False) -> list[dict[str, Any]]:
        """``[{"keyframe", "pose" (4x4 rows), "scale"}]`` of the robot's corrected keyframes (empty: not merged)."""
        result = self.optimize(wait)
        return [{"keyframe": n.keyframe, "pose": result.pose_matrix(n).tolist(), "scale": T.s}
                for n, T in sorted(result.poses.items()) if n.robot == robot]

    # ------------------------------------------------------------------------------------------- admin actions
    def set_anchor(self, robot: str) -> None:
        """Makes ``robot``'s map frame the global frame (an admin's action): every map is re-expressed in it by the
        next solution.

        Raises:
            ConfigError: an unknown robot, or one without keyframes (its frame would hold nothing).
        """
        if self.store.last_keyframe(robot) is None:
            raise ConfigError(f"robot {robot!r} has no keyframes: its map cannot be the global frame")
        with self._lock:
            self.anchor = self.store.set_anchor(robot, replace=True)
            self._graph.set_anchor(self.anchor)
            self._anchor_merged = self.anchor  # the admin's choice: not moved by a first merge of others
        log.warning("admin: the anchor (global frame) is now robot %s; every map is re-expressed in its frame", robot)
        self.optimizer.changed()

    def reset(self, robot: str, keep_keyframes: bool = True) -> int:
        """Starts the robot again (an admin's action; also what releases a quarantined one): its recognition from
        nothing (``FleetRecognizer.forget``: its folder moved aside), and, unless ``keep_keyframes``, its stored
        keyframes, their edges, overlaps and transform dropped (its next keyframe id and timestamp may then be any).

        Returns:
            Keyframes dropped.

        Raises:
            ConfigError: an unknown robot. ConflictError: dropping the anchor's keyframes (name another first).
        """
        if not self.has_robot(robot):
            raise ConfigError(f"unknown robot {robot!r}")
        if not keep_keyframes and robot == self.anchor:
            raise ConflictError(f"robot {robot!r} is the anchor (the global frame); name another anchor first")
        dropped = 0
        with self._submit_lock(robot):
            if self.recognizer is not None:
                self.recognizer.forget(robot)
            if not keep_keyframes:
                dropped = self.store.drop_keyframes(robot)
                with self._lock:
                    self._graph = self._graph.without({robot})
            self.quarantined.pop(robot, None)
        log.warning("admin: robot %s reset (recognition restarted; %s)", robot,
                    "stored keyframes kept" if keep_keyframes else f"{dropped} stored keyframes dropped")
        self.optimizer.changed()
        return dropped

    def retire(self, robot: str, keep_keyframes: bool = True) -> int:
        """Retires a robot (an admin's action): its token stops working at once, its name stays taken; its keyframes
        stay in the map unless ``keep_keyframes`` is False (then dropped as ``reset`` does). ``rotate_token`` brings
        it back.

        Returns:
            Keyframes dropped.
        """
        if not self.has_robot(robot):
            raise ConfigError(f"unknown robot {robot!r}")
        dropped = 0 if keep_keyframes else self.reset(robot, keep_keyframes=False)
        self.store.retire(robot)
        self._forget_tokens(robot)
        log.warning("admin: robot %s retired (its token revoked; %s)", robot,
                    "stored keyframes kept" if keep_keyframes else f"{dropped} stored keyframes dropped")
        return dropped

    def rotate_token(self, robot: str) -> str:
        """A new token for the robot (an admin's action; the old one stops working at once; a retired robot is
        active again); returns it (shown once, stored hashed)."""
        token = f"{robot}.{secrets.token_urlsafe(32)}"
        self.store.set_token(robot, token)
        self._forget_tokens(robot)
        log.warning("admin: robot %s has a new token (the old one is revoked)", robot)
        return token

    def close(self) -> None:
        """Stops the optimizer, closes the robots' databases and the store."""
        self.optimizer.close()
        if self.recognizer is not None:
            self.recognizer.close()
        self.store.close()
