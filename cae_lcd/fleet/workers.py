"""Per-robot work on several processes: robots sharded by name over Ray workers, each a ``FleetRecognizer``.

The service calls a recognizer through five methods (``has``, ``check``, ``process``, ``resume``, ``close``, and
``committed`` when the recognizer has it);
``FleetRecognizer`` is the in-process one, ``RayRecognizer`` the same interface over ``workers`` Ray actors (a local
Ray started with that many CPUs, or a cluster at ``ray_address``). Robot ``NAME`` belongs to shard
``crc32(NAME) % workers``: that actor decodes, gates, encodes, extracts features, searches and verifies its
keyframes, and keeps its keyframe database under the shared state folder. Each keyframe's pose and features are
copied to the other actors (``FleetRecognizer.export`` -> ``adopt``) once the service has stored it (``committed``),
so every robot is matched against every other one; its searched code too when the place memory is ``local`` (each
worker's own), not when it is ``milvus`` (``cae_lcd.fleet.places.MilvusPlaces``): then every worker inserts its own robots'
entries in one collection and searches everyone's. With ``milvus`` and no ``uri``, the milvus-lite folder
``STATE/places.db`` is served by one more named actor (``_PlacesHost``, started once per state folder like the
shards, on loopback: the workers of one machine; give ``uri: http://HOST:19530``, a Milvus server, for a cluster of
machines), and every worker connects to it. Of another worker's robot an actor keeps the
features of the ``adopted_features`` (64) most recently used keyframes and asks the owner for the others when a match
needs them (``FETCH``): a worker's memory does not grow by every other robot's features. Keyframes of robots on
different shards are processed at the same time (``parallel_robots``): the service then serialises keyframes per robot
only.

Several front-end replicas on one Ray cluster share the workers (named after the state folder). A worker that dies
is started again on its next request, and its robots continue there: the new actor reopens their
keyframe databases from the state folder (adding their entries to a shared place memory again: upserts) and the
surviving actors copy their robots' keyframes to it. The actor serving milvus-lite is not started again: if it dies,
the place memory is unreachable until the front ends and their workers restart (its folder keeps what it held).
"""

from __future__ import annotations

import logging
import threading
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from cae_lcd.core.cluster import start_ray
from cae_lcd.core.errors import ConfigError

from .places import FLEET_PLACES
from .recognition import FleetRecognizer, Recognition
from .store import EdgeRecord, OverlapRecord

__all__ = ["RayRecognizer", "shard_of", "shard_name", "host_name", "create_recognizer"]

log = logging.getLogger(__name__)


NAMESPACE = "cae-lcd-fleet"  #: the Ray namespace of the workers
FETCH = "fetch"  #: the workers' concurrency group that serves other workers' ``features`` requests


def shard_of(robot: str, workers: int) -> int:
    """The worker a robot belongs to: ``crc32(name) % workers`` (the same in every process and run)."""
    return zlib.crc32(robot.encode("utf-8")) % workers


def shard_name(state_dir: str, index: int, workers: int) -> str:
    """The Ray actor name of shard ``index``: named after the state folder, so that front-end replicas on one Ray
    cluster share it (the first replica starts it, the others attach) and workers find each other."""
    return f"fleet-{zlib.crc32(state_dir.encode()):08x}-{index}-of-{workers}"


def host_name(state_dir: str) -> str:
    """The Ray actor name of the state folder's milvus-lite server (``_PlacesHost``): replicas share it as the
    shards."""
    return f"fleet-{zlib.crc32(state_dir.encode()):08x}-places"


class _PlacesHost:
    """The body of the Ray actor that serves a milvus-lite folder to every worker (``serve_lite``, in its threads)."""

    def __init__(self, path: str, lite_buffer_kb: int) -> None:
        from retrieval.milvus_index import serve_lite

        self.uri = serve_lite(path, lite_buffer_kb)

    def address(self) -> str:
        """``http://127.0.0.1:PORT``: where the workers connect."""
        return self.uri


class _Shard:
    """The body of one Ray actor: a ``FleetRecognizer`` that owns the robots of shard ``index``. Another robot's
    keyframe features it no longer keeps are asked of that robot's worker, in its ``FETCH`` group (threads of their
    own: two workers asking each other at once do not wait on each other's keyframe)."""

    def __init__(self, state_dir: str, conf: dict[str, Any] | None, index: int, workers: int) -> None:
        self.state_dir, self.workers = state_dir, workers
        self._owners: dict[int, Any] = {}
        self.rec = FleetRecognizer(state_dir, conf, owns=lambda name: shard_of(name, workers) == index,
                                   fetch=self._fetch)

    def _fetch(self, robot: str, keyframe: int) -> Any:
        """The features of another worker's keyframe, from that worker."""
        import ray

        i = shard_of(robot, self.workers)
        try:
            return ray.get(self._owner(i).features.options(concurrency_group=FETCH).remote(robot, [keyframe]))[0]
        except ray.exceptions.RayActorError:  # started again since (``RayRecognizer._on_shard``): its new handle
            self._owners.pop(i, None)
            return ray.get(self._owner(i).features.options(concurrency_group=FETCH).remote(robot, [keyframe]))[0]

    def _owner(self, index: int) -> Any:
        """The actor of shard ``index`` (looked up by name once)."""
        import ray

        if index not in self._owners:
            self._owners[index] = ray.get_actor(shard_name(self.state_dir, index, self.workers), namespace=NAMESPACE)
        return self._owners[index]

    def features(self, robot: str, keyframes: list[int]) -> list:
        return self.rec.features(robot, keyframes)

    def owned(self) -> list[str]:
        return self.rec.owned()

    def export(self, robot: str) -> list:
        return self.rec.export(robot)

    def adopt(self, robot: str, shared: list) -> None:
        self.rec.adopt(robot, shared)

    def has(self, robot: str, keyframe: int) -> bool:
        return self.rec.has(robot, keyframe)

    def check(self, robot: str, K: np.ndarray | None) -> None:
        self.rec.check(robot, K)

    def check_retry(self, robot: str, keyframe: int, image: np.ndarray) -> None:
        self.rec.check_retry(robot, keyframe, image)

    def resume(self, overlaps: list[OverlapRecord], edges: list[EdgeRecord]) -> None:
        self.rec.resume(overlaps, edges)

    def process(self, robot: str, keyframe: int, *args: Any) -> tuple[Recognition, list]:
        found = self.rec.process(robot, keyframe, *args)
        return found, ([] if found.gated else self.rec.export(robot, [keyframe]))

    def forget(self, robot: str) -> None:
        self.rec.forget(robot)

    def quarantined(self) -> dict[str, str]:
        return dict(self.rec.quarantined)

    def close(self) -> None:
        self.rec.close()


class RayRecognizer:
    """``FleetRecognizer``'s interface over Ray actors, robots sharded by name (see the module doc).

    Args:
        state_dir: the server's state folder, reachable by every worker (shared storage on a cluster).
        conf: overrides of ``FleetRecognizer.default_conf`` (every worker gets the same).
        workers: number of actors (shards), >= 1.
        ray_address: a Ray cluster to join (``ray://HOST:10001`` or ``auto``); None: a local Ray with ``workers`` CPUs
            (unless Ray is already running in this process).

    Raises:
        ConfigError: a bad conf or worker count (before any worker starts).
    """

    parallel_robots = True  #: keyframes of different robots may be processed at the same time

    def __init__(self, state_dir: str | Path, conf: dict[str, Any] | None = None, workers: int = 2,
                 ray_address: str | None = None) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ConfigError(f"workers must be an integer >= 1; got {workers!r}")
        places = FleetRecognizer.resolve(conf)["places"]  # a bad conf is refused here, before any worker starts
        self._ray, _ = start_ray(ray_address, workers)  # this process's Ray, the cluster's, or a new local one
        self.state_dir, self.conf, self.workers = str(Path(state_dir).resolve()), conf, workers
        self._host = None
        self.conf = self._host_places(places)
        self._actor = self._ray.remote(num_cpus=1, max_restarts=0, concurrency_groups={FETCH: 1})(_Shard)
        self._shards = [self._start(i) for i in range(workers)]
        self._resumed: tuple[list[OverlapRecord], list[EdgeRecord]] | None = None
        self._recorded: set[frozenset[str]] = set()  # robot pairs whose overlap was reported (by either worker)
        self._pending: dict[str, list] = {}  # robot -> its latest keyframe, copied to the others with its next one
        self._lock = threading.Lock()
        self._share_all()

    def _host_places(self, places: dict[str, Any]) -> dict[str, Any] | None:
        """The workers' conf: with a milvus-lite place memory (no server ``uri``), its folder served once by a named
        actor (``host_name``; no CPU reserved: the workers' calls keep it busy) and its URI given to every worker."""
        path = FLEET_PLACES.get(places["name"]).lite_path(places, self.state_dir)
        if path is None:
            return self.conf
        self._host = self._ray.remote(num_cpus=0, max_restarts=0)(_PlacesHost).options(
            name=host_name(self.state_dir), namespace=NAMESPACE, get_if_exists=True).remote(str(path),
                                                                                            places["lite_buffer_kb"])
        uri = self._ray.get(self._host.address.remote())
        log.info("fleet place memory: milvus-lite %s served on %s to every worker", path, uri)
        conf = dict(self.conf or {})
        return {**conf, "places": {**(conf.get("places") or {}), "uri": uri}}

    def _start(self, index: int) -> Any:
        """Shard ``index``'s actor (``shard_name``: replicas on one Ray cluster share it)."""
        return self._actor.options(name=shard_name(self.state_dir, index, self.workers), namespace=NAMESPACE,
                                   get_if_exists=True).remote(self.state_dir, self.conf, index, self.workers)

    def _share_all(self, to: list[int] | None = None) -> None:
        """Copies every owned robot's keyframes to the other shards (all, or the shards in ``to``)."""
        ray = self._ray
        owned = ray.get([s.owned.remote() for s in self._shards])
        for i, robots in enumerate(owned):
            targets = [j for j in (range(self.workers) if to is None else to) if j != i]
            for robot in robots if targets else []:
                shared = ray.get(self._shards[i].export.remote(robot))
                ray.get([self._shards[j].adopt.remote(robot, shared) for j in targets])

    def _on_shard(self, robot: str, method: str, *args: Any) -> Any:
        """Runs ``method`` on the robot's shard; a dead worker is started again (its robots reopened from the state
        folder, the other robots' keyframes copied to it) and asked once more."""
        ray = self._ray
        i = shard_of(robot, self.workers)
        try:
            return ray.get(getattr(self._shards[i], method).remote(robot, *args))
        except ray.exceptions.RayActorError:
            log.warning("fleet worker %d died; starting it again (its robots continue from the state folder)", i)
            self._shards[i] = self._start(i)
            if self._resumed is not None:
                ray.get(self._shards[i].resume.remote(*self._resumed))
            self._share_all(to=[i])
            return ray.get(getattr(self._shards[i], method).remote(robot, *args))

    def has(self, robot: str, keyframe: int) -> bool:
        """True when the robot's database already holds ``keyframe`` (or a later one)."""
        return bool(self._on_shard(robot, "has", keyframe))

    def check(self, robot: str, K: np.ndarray | None) -> None:
        """Refuses intrinsics that differ from the robot's first ones; changes nothing."""
        self._on_shard(robot, "check", K)

    def check_retry(self, robot: str, keyframe: int, image: np.ndarray) -> None:
        """Refuses (``ConflictError``) a retry of a stored keyframe with another image; changes nothing."""
        self._on_shard(robot, "check_retry", keyframe, image)

    def process(self, robot: str, keyframe: int, timestamp: float, pose: np.ndarray, image: np.ndarray,
                K: np.ndarray | None = None, depth: np.ndarray | None = None) -> Recognition:
        """``FleetRecognizer.process`` on the robot's worker. The keyframe is copied to the other workers by
        ``committed`` (the service calls it once the keyframe is stored: an edge to it never precedes it in the store).
        """
        self.committed(robot)  # a keyframe the service did not report (refused by the store): shared all the same
        found, shared = self._on_shard(robot, "process", keyframe, timestamp, pose, image, K, depth)
        with self._lock:  # both robots' workers may accept the same overlap: it is reported once
            if shared:
                self._pending[robot] = shared
            fresh = [o for o in found.overlaps if frozenset((o.robot_a, o.robot_b)) not in self._recorded]
            self._recorded.update(frozenset((o.robot_a, o.robot_b)) for o in fresh)
        found.overlaps = fresh
        return found

    def committed(self, robot: str) -> None:
        """The service stored the robot's latest keyframe: it is copied to the other workers now (before, another
        robot's edge to it could reach the store first)."""
        with self._lock:
            shared = self._pending.pop(robot, None)
        if shared:
            owner = shard_of(robot, self.workers)
            self._ray.get([s.adopt.remote(robot, shared) for j, s in enumerate(self._shards) if j != owner])

    def resume(self, overlaps: list[OverlapRecord], edges: list[EdgeRecord]) -> None:
        """Every worker continues the accepted overlaps and the stored edges' counts."""
        self._resumed = (overlaps, edges)
        self._recorded.update(frozenset((o.robot_a, o.robot_b)) for o in overlaps)
        self._ray.get([s.resume.remote(overlaps, edges) for s in self._shards])

    @property
    def quarantined(self) -> dict[str, str]:
        """Robots whose files their worker could not read (name -> why)."""
        return {k: v for q in self._ray.get([s.quarantined.remote() for s in self._shards]) for k, v in q.items()}

    def forget(self, robot: str) -> None:
        """``FleetRecognizer.forget`` on every worker (its owner moves its folder aside)."""
        self._ray.get([s.forget.remote(robot) for s in self._shards])

    def close(self) -> None:
        """Closes every worker's databases and stops the workers (those shared with other replicas too)."""
        for s in self._shards:
            try:
                self._ray.get(s.close.remote())
            except self._ray.exceptions.RayActorError:
                log.debug("a fleet worker was already gone at close (stopped by another replica)")
            self._ray.kill(s)
        if self._host is not None:  # after the workers: they close their connections first
            self._ray.kill(self._host)


def create_recognizer(state_dir: str | Path, conf: dict[str, Any] | None = None, descriptor: Any = None,
                      workers: int = 1, ray_address: str | None = None) -> FleetRecognizer | RayRecognizer:
    """The in-process recognizer (``workers`` 1 and no cluster), else the Ray one (``descriptor`` is then built by
    each worker)."""
    if workers == 1 and not ray_address:
        return FleetRecognizer(state_dir, conf, descriptor)
    return RayRecognizer(state_dir, conf, workers, ray_address)
