"""Place recognition across a fleet: the ``detect`` pipeline on every robot's keyframes, intra-robot loops and
inter-robot overlaps, each turned into a pose-graph edge (a similarity from 3D-3D matches).

- One ``retrieval.LoopDetector`` per robot, its keyframes in ``STATE/robots/NAME/keyframes.h5`` (resumed on start),
  all sharing one global descriptor (the CAE encoder is loaded once per server). It reports the robot's own loops,
  with its usual recent-frame exclusion, and **calibrates itself on the robot's own stream** (``retrieval.online``,
  the detector's default): a warm-up of ``2 x search.exclude_recent`` keyframes (at least 40) in which it accepts
  nothing, then the whitening, the nulls and the decision fitted on the robot's keyframes and refitted at
  doublings and on drift, its state kept in the robot's store (a restart resumes it, no second warm-up).
  ``detector.calibration.enabled: false`` runs the fixed policy instead (``policy.min_inliers``).
- Inter-robot: the query's entry in the fleet's one place memory (``cae_lcd.fleet.places``: every robot's entries
  keyed by robot and keyframe, ``local`` in this process or one ``milvus`` collection shared by every worker; no
  recency exclusion: another robot's frame is never "recent"). **One code space**: every entry is made by the
  memory from the keyframe's raw code (``FrameResult.code``; after a restart, the raw codes an online robot's store
  keeps) in the memory's own fixed whitening (the weights', none for the shipped CAE weights: the raw code), never
  from ``FrameResult.entry``, which a robot's refit moves into its stream's whitening. The top-``cross.search_k``
  of the other robots (of the keyframes this recognizer has: a shared memory may hold another worker's newest one
  before the service stored it), of each other robot at most ``cross.k``, at most ``cross.budget`` in all (the most
  similar: ``cae_lcd.fleet.budget``), are verified by the robot's detector's verifier (SIFT + geometry); the best
  verified candidate of each other robot is a **match** when it passes the pair's rule, and each robot pair's
  matches feed ``OverlapTracker``: an overlap is accepted after a run of consecutive matching keyframes (matches
  within ``overlap.max_match_gap`` keyframes of each other); from then on every match becomes an edge (at most
  ``max_edges_per_pair``).
- **The pair's rule, calibrated** (robots calibrating online): a match needs more inliers than every hard negative
  that *either* robot's calibration measured on its own stream (its pair null ``samples["hard_inliers"]``, about
  750-1200 verified far-side pairs: above its largest, the empirical p-value ``1 / (n + 1)`` is the smallest it can
  show; and at least its floor, ``calibration.min_inliers``), and the run must be as long as *either* robot's own
  fused decision needs of such frames to accept a loop (``retrieval.calibrate.run_needed``: 5 on KITTI), at least
  ``overlap.required``: ``certified_match`` of each robot, the stricter of the two (``_cross_rule``). Nothing counts
  (nothing is verified) until both robots are out of their warm-up, nor with a robot on the score path (too few
  local features to verify). **Catch-up**: on a robot's first certified keyframe, its keyframes from before (its
  warm-up, at most ``cross.catch_up``) are matched against every robot with which the pair's rule is then in force,
  in keyframe order, each pair's run going on into the live keyframes (``_catch_up_due``): robots that met only in
  their warm-ups (a fleet leaving one depot) find their overlap. The other direction needs no second pass (the other
  robot's catch-up, or its queries once certified), so every pair of keyframes is checked once. The promise, and
  what it rests on: each match of the run is as strong as the strongest non-loop pair both robots measured, and the
  run is the one each robot's own calibration needs to keep its expected false loops under
  ``calibration.expected_false_loops / 2`` (counted with the tests of its own stream, not the fleet's: a query tests
  every other robot, so with many robots the cross-robot tests grow with the robot pairs, which this does not
  count); cross-robot pairs are taken to be no likelier to look alike than a robot's own far-side pairs (the same
  camera model; a fleet of unlike cameras breaks this), and the frames of one run are not independent, so the rule
  is checked on real look-alikes: KITTI 00 vs 07 as two robots accepts no overlap (with the floor alone, 12 inliers
  x 3, it does: ``tests/fleet/test_recognition_online.py``). With the fixed policy the rule is ``cross.min_inliers``
  inliers and ``overlap.required`` matches.
- A loop edge takes the detector's own verification of the pair (``FrameResult.verification``: its matches and
  transform); nothing is verified twice. A delayed loop (``FrameResult.confirmed``: a run, or a refit, certified an
  earlier keyframe's loop; the detector reports each once) is verified by the detector's verifier on the two
  keyframes' features (``LoopDetector.keyframe_features``) and becomes a loop edge like the others.
- **Cost**: a robot's fit or refit, and its catch-up, run on the keyframe that triggers them, inside that keyframe's
  request (a robot's requests are serialised, other robots' go on: ``parallel_robots``); the server bounds the
  body's size and read time (``cae_lcd.fleet.limits``), and the catch-up by ``cross.catch_up`` keyframes of
  ``cross.budget`` candidates each. Measured (quiet 2-core machine, ``python -m bench.fleet_online --set 90one``):
  KITTI 90 as one robot of 200 keyframes, 32 ms a keyframe (median; mean 41), the worst request the refit at its
  200th keyframe, 1.3 s (the fixed policy: 31 / 30 ms, worst 0.16 s); 61 loop edges, all true (fixed: 58). A
  catch-up: about 20 ms a keyframe caught up (``--set 90split``: B's fit and catch-up of 99 keyframes, 2.4 s). A
  refit's request grows with the map up to ``calibration.max_frames`` (2000: a fit reads at most that many frames
  and decides again at most the newest that many): KITTI 00 lap after lap as one robot (``--set 00laps --keyframes
  1700``), the refits at 380, 760 and 1520 keyframes took 2.2, 3.4 and 5.6 s. A request that outlasts
  ``FleetClient``'s 30 s default timeout is stored all the same, and the robot's retry is answered from the store.
- An edge's similarity: 3D points of the matched features on both sides (the depth map when the keyframe came with
  one, else triangulated from the robot's own neighbouring keyframe with its local poses), then ``estimate_overlap``.

Camera intrinsics are per robot (the first keyframe's), kept in ``STATE/robots/NAME/camera.json``. 3D points of at
most ``points_cache`` keyframes per robot are kept in memory. Local features are the detector's
(``LoopDetector.keyframe_features``): with ``detector.runtime.features: database`` (the default here) they are read
back from the robot's keyframe database, at most ``detector.runtime.feature_cache`` kept per robot; ``memory`` keeps
them all. Points from depth maps are kept in memory only: after a restart, or once dropped from the cache, keyframes
that had one fall back to triangulation. The fleet reaches no private attribute of a ``LoopDetector``
(``tests/fleet/test_recognition.py`` checks it).
"""

from __future__ import annotations

import functools
import json
import logging
import os
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cae_lcd.core.conf import ConfigError, Float, Int, check_conf, merge_conf
from cae_lcd.core.errors import ConflictError
from cae_lcd.core.files import write_text_atomic
from cae_lcd.core.images import check_image, fingerprint
from retrieval.calibrate import Calibration, run_needed
from retrieval.descriptors import GlobalDescriptor, create_descriptor
from retrieval.detector import LoopDetector, resolve_conf, weights_whitening
from verify.verifier import Verification

from .budget import shortlist
from .places import create_fleet_places, resolve_places
from .overlap import OverlapTracker, PointTriangulator, estimate_overlap, points_from_depth
from .sim3 import Sim3, Sim3Ransac
from .store import EdgeRecord, OverlapRecord

__all__ = ["FleetRecognizer", "Recognition", "SharedKeyframe", "CAMERA_FORMAT_VERSION", "certified_match",
           "FIXED_POLICY"]

log = logging.getLogger(__name__)

CAMERA_FORMAT_VERSION = 1  #: format of ``camera.json``
#: the recognition conf of the fixed policy (``policy.min_inliers``, ``cross.min_inliers``) for robots whose streams
#: are shorter than an online warm-up (``2 x search.exclude_recent`` keyframes: nothing accepted there): the demo's,
#: short tests and benches; merged into a conf (``{**FIXED_POLICY, ...}``), never modified
FIXED_POLICY: dict[str, Any] = {"detector": {"calibration": {"enabled": False}}}


@dataclass
class Recognition:
    """What one keyframe found: loop and overlap edges (keyframe ``b`` is the query) and newly accepted overlaps."""

    edges: list[EdgeRecord] = field(default_factory=list)
    overlaps: list[OverlapRecord] = field(default_factory=list)
    gated: bool = False  #: the quality gate refused the image (no place memory entry)


@dataclass(frozen=True)
class SharedKeyframe:
    """What another recognizer needs of a keyframe to match it across robots (``export`` -> ``adopt``)."""

    entry: np.ndarray | None  #: ``(d,)`` the searched code (None: the place memory is shared, it is there already)
    features: Any  #: ``verify.features.Features`` of the keyframe (None: fetched from its owner when needed)
    pose: np.ndarray  #: ``(4, 4)`` local pose
    K: np.ndarray | None  #: ``(3, 3)`` the robot's intrinsics
    certified: tuple[int, int] | None = None  #: ``certified_match`` of its robot's calibration when exported
    #                                            (None: not calibrated yet, or the fixed policy)


class _Adopted:
    """Stands in for the detector of a robot another recognizer owns: the local features of its ``cache`` most
    recently used keyframes; the others are fetched from the owner (``fetch(keyframe)``) when a match needs them."""

    def __init__(self, cache: int, fetch: Callable[[int], Any] | None = None) -> None:
        self.cache, self.fetch = max(1, int(cache)), fetch
        self.features: OrderedDict[int, Any] = OrderedDict()
        self.certified: tuple[int, int] | None = None  # its owner's latest ``certified_match`` (``SharedKeyframe``)

    def remember(self, frame_id: int, features: Any) -> None:
        """Keeps a keyframe's features, dropping the least recently used past ``cache``."""
        self.features[int(frame_id)] = features
        self.features.move_to_end(int(frame_id))
        while len(self.features) > self.cache:
            self.features.popitem(last=False)

    def keyframe_features(self, frame_id: int) -> Any:
        """The adopted keyframe's features (``LoopDetector.keyframe_features``'s interface), fetched if not kept.

        Raises:
            KeyError: not kept, and nothing to fetch them from.
        """
        k = int(frame_id)
        if k in self.features:
            self.features.move_to_end(k)
            return self.features[k]
        if self.fetch is None:
            raise KeyError(k)
        features = self.fetch(k)
        self.remember(k, features)
        return features

    def close(self) -> None:
        """Nothing to release."""


def certified_match(cal: Calibration | None, window: int) -> tuple[int, int] | None:
    """What a robot with calibration ``cal`` certifies a cross-robot overlap with: ``(inliers, run)``, each match
    above every hard negative its stream measured (``samples["hard_inliers"]``, the pair null, where its empirical
    p-value is its smallest, ``1 / (n + 1)``; at least its floor), and ``run`` consecutive such matches, the run its
    own fused decision needs of such frames to accept a loop (``retrieval.calibrate.run_needed``; ``window``: its
    ``search.exclude_recent``). None: nothing is certified (no calibration decides yet: the warm-up; the score path,
    where nothing is verified; a null with no sample, or one under which no run of its span suffices)."""
    run = None if cal is None else run_needed(cal, window)
    if run is None:
        return None
    return max(int(cal.inlier_null["floor"]), int(np.max(cal.samples["hard_inliers"])) + 1), run


def _image_fingerprint(image: np.ndarray) -> str:
    """``cae_lcd.core.images.fingerprint`` of a decoded image's shape and pixels (what a retry is compared by)."""
    return fingerprint(repr((image.shape, image.dtype.str)).encode() + np.ascontiguousarray(image).tobytes())


class _Robot:
    """One robot's detector, intrinsics, local poses and keyframe ids (its entries are in the fleet's place memory)."""

    def __init__(self, detector: LoopDetector, K: np.ndarray | None, points_cache: int = 256) -> None:
        self.detector, self.K, self.points_cache = detector, K, points_cache
        self.poses: dict[int, np.ndarray] = {}  # keyframe -> (4, 4) local pose
        self.ids: list[int] = []  # keyframes in the place memory (passed the gate), ascending
        self.points: OrderedDict[int, np.ndarray] = OrderedDict()  # keyframe -> (N, 3) feature points (LRU)
        self.last: tuple[int, np.ndarray] | None = None  # the latest keyframe's searched entry (for ``export``)
        #: keyframes sent before the robot was first certified, not yet matched across (None: caught up)
        self.unchecked: list[int] | None = []
        self.lock = threading.Lock()  # held while its detector processes a keyframe, and to read its features

    def remember_points(self, keyframe: int, points: np.ndarray) -> np.ndarray:
        """Caches a keyframe's 3D points, dropping the least recently used past ``points_cache``."""
        self.points[keyframe] = points
        self.points.move_to_end(keyframe)
        while len(self.points) > self.points_cache:
            self.points.popitem(last=False)
        return points

    def neighbour(self, keyframe: int) -> int | None:
        """The keyframe in the place memory nearest to ``keyframe`` (another one), None if there is none."""
        others = [i for i in self.ids if i != keyframe]
        return min(others, key=lambda i: (abs(i - keyframe), i)) if others else None


class FleetRecognizer:
    """Loops and overlaps of every robot's keyframes (see the module doc).

    Keyframes of different robots may be processed at once (``parallel_robots``; callers serialise each robot's own):
    a robot's detector (decode, gate, encode, features, its own search and verification, its database) and the
    verification of its cross-robot candidates run outside the lock that guards what robots share (the place memory,
    the overlap rules, the edges); the heavy work is in OpenCV and torch, which release the GIL.

    Args:
        state_dir: the server's state folder (robots' databases go in ``robots/NAME/``).
        conf: overrides of ``default_conf``.
        descriptor: an already built global descriptor; None: built once from ``detector.descriptor``.
        owns: which robots this recognizer opens from the state folder (None: all); the others' keyframes come
            through ``adopt`` (``cae_lcd.fleet.workers`` shards robots over several recognizers this way).
        fetch: ``fetch(robot, keyframe)`` -> the local features of another recognizer's keyframe that this one no
            longer keeps (``adopted_features``); None: only those kept are matched.

    Raises:
        ConfigError: a bad conf. DatabaseError: a damaged robot database.
    """

    default_conf: dict[str, Any] = {
        # the LoopDetector conf of every robot, merged onto the detector's defaults: each robot's detector calibrates
        # itself on its own stream (retrieval.online; calibration: {enabled: false} runs the fixed policy)
        "detector": {"calibration": {"features_px": None},  # local features at features.resize_max (512 px), as
                     #   the fixed policy's: an edge's similarity needs 3D points triangulated from them, and at the
                     #   calibrated default (384 px) KITTI 90 as two robots gave 6 overlap edges, 19 at 512 px
                     "runtime": {"features": "database",  # features read back from its database when needed,
                                 "feature_cache": 64,  # at most this many kept per robot (~64 kB each)
                                 "flush_every": 16}},  # keyframes a robot's store holds in memory (features
    #                              included, ~70 kB each) before it writes them into its columns: 256 (a detector's
    #                              default) would be up to 18 MB a robot; every keyframe is in the store's log at once
        "cross": {
            "search_k": 64,  # entries of other robots searched in the fleet's place memory per query
            "k": 3,  # candidates of each other robot verified per query
            "budget": 8,  # candidates verified per query over all other robots, the most similar (0: no bound)
            "min_score": 0.0,  # candidates under this cosine similarity are not verified
            "min_matches": 5,  # putative matches a candidate needs
            "min_inliers": 50,  # fixed policy only (detector.calibration.enabled: false): the geometric inliers a
            #                     cross-robot match needs (chosen on KITTI at 512 px); calibrated, the robots' own
            #                     measured nulls say it (above every hard negative of both: the module doc)
            "catch_up": 200,  # calibrated only: when a robot is first certified, its keyframes from before (its
            #                   warm-up; at most this many, the newest) are matched across then (0: none)
        },
        "places": {"name": "local",  # the place memory across robots (cae_lcd.fleet.places): local (in each process)
                   "index": {"name": "fp16"}},  # or milvus (one collection every worker shares: uri, collection, ...)
        "overlap": OverlapTracker.default_conf,  # n-consecutive-match acceptance of an overlap
        "triangulation": PointTriangulator.default_conf,  # 3D points from a robot's neighbouring keyframe
        "sim3": Sim3Ransac.default_conf,  # RANSAC of an edge's similarity from 3D-3D matches
        "min_points": 20,  # 3D-3D RANSAC inliers an edge needs
        "max_edges_per_pair": 30,  # overlap edges kept per robot pair (the accepting run's first)
        "points_cache": 256,  # keyframes' 3D feature points kept in memory per robot (least recently used dropped)
        "adopted_features": 64,  # of a robot another Ray worker owns: local features kept per robot (least recently
        #                          used dropped; the others are fetched from its worker when a match needs them)
    }
    conf_rules: dict[str, Any] = {
        "cross": {"search_k": Int(1, 100_000), "k": Int(1, 1000), "budget": Int(0, 100_000), "min_score": Float(-1, 1), "min_matches": Int(0),
                  "min_inliers": Int(0), "catch_up": Int(0, 100_000)},
        "overlap": OverlapTracker.conf_rules, "triangulation": PointTriangulator.conf_rules,
        "sim3": Sim3Ransac.conf_rules, "min_points": Int(3), "max_edges_per_pair": Int(1), "points_cache": Int(1),
        "adopted_features": Int(1)}

    def __init__(self, state_dir: str | Path, conf: dict[str, Any] | None = None,
                 descriptor: GlobalDescriptor | None = None, owns: Callable[[str], bool] | None = None,
                 fetch: Callable[[str, int], Any] | None = None) -> None:
        self.conf = self.resolve(conf)
        self.fetch = fetch
        self.detector_conf = self.conf["detector"]
        cal = self.detector_conf["calibration"]
        self._calibrated = cal["enabled"] and cal["online"]  # every robot's detector calibrates on its stream
        self.root = Path(state_dir) / "robots"
        self.descriptor = descriptor or create_descriptor(self.detector_conf["descriptor"])
        self.places = create_fleet_places(self.descriptor, weights_whitening(self.detector_conf, self.descriptor),
                                          self.detector_conf, self.conf["places"], state_dir)
        self.tracker = OverlapTracker(self.conf["overlap"])
        self.triangulator = PointTriangulator(self.conf["triangulation"])
        self.robots: dict[str, _Robot] = {}
        self._checks: dict[tuple[str, str], dict[int, Verification]] = {}  # recent verified matches per robot pair
        self._edges: dict[tuple[str, str], int] = {}
        self._recorded: set[frozenset[str]] = set()  # robot pairs whose overlap was recorded (this run)
        self._lock = threading.RLock()  # what robots share: robots, places, tracker, checks, edges, points
        #: robots whose files cannot be read (name -> why, one line): not opened, the others are (``forget`` resets)
        self.quarantined: dict[str, str] = {}
        self._owns = owns
        for folder in sorted(self.root.iterdir()) if self.root.is_dir() else []:
            if owns is None or owns(folder.name):
                self._open_at_start(folder)

    def _open_at_start(self, folder: Path) -> None:
        """Opens a robot's folder found at start-up; one that cannot be read is quarantined (one log line), so that
        one robot's damaged files never stop the others."""
        name = folder.name
        if name.startswith("."):  # .reset/: folders moved aside by ``forget``
            return
        try:
            if not folder.is_dir():
                raise ConfigError(f"{folder} is not a folder")
            if (folder / "camera.json").exists():
                self._open(name, None)
        except Exception as err:  # noqa: BLE001 -- any damage (JSON, HDF5, OS): this robot only
            self.robots.pop(name, None)
            # the first clause of the first line, paths from the state folder on (an answer to a robot holds it)
            why = (str(err).strip().splitlines() or [type(err).__name__])[0].split("; ")[0][:300]
            why = why.replace(f"{self.root.parent}{os.sep}", "")
            self.quarantined[name] = f"{type(err).__name__}: {why}"
            log.error("robot %s quarantined: its files cannot be read (%s); its requests are refused until an admin "
                      "resets or drops it", name, self.quarantined[name])

    @classmethod
    def resolve(cls, conf: dict[str, Any] | None) -> dict[str, Any]:
        """``conf`` merged onto ``default_conf`` and checked (``detector`` by the detector's own rules).

        Raises:
            ConfigError: an unknown key or a bad value.
        """
        conf = dict(conf or {})
        user_detector = conf.pop("detector", None)  # checked by the detector's own rules (its units' sections)
        user_places = conf.pop("places", None)  # by its kind's rules (cae_lcd.fleet.places)
        out = merge_conf({k: v for k, v in cls.default_conf.items() if k not in ("detector", "places")}, conf,
                         "recognition")
        check_conf(out, cls.conf_rules, "recognition")
        out["detector"] = resolve_conf(merge_conf(cls.default_conf["detector"], user_detector, strict=False))
        out["places"] = resolve_places(user_places)
        return out

    def _open(self, name: str, K: np.ndarray | None) -> _Robot:
        """The robot's detector, resumed from its database; ``K`` is the stored one when there is a ``camera.json``
        (written by ``process`` once the robot's first keyframe is accepted)."""
        folder = self.root / name
        camera = folder / "camera.json"
        if camera.exists():
            stored = json.loads(camera.read_text())
            if not isinstance(stored, dict) or stored.get("format_version") != CAMERA_FORMAT_VERSION:
                raise ConfigError(f"{camera}: format_version {stored.get('format_version')} is not "
                                  f"{CAMERA_FORMAT_VERSION}")
            K = None if stored["K"] is None else np.asarray(stored["K"], np.float64)
        folder.mkdir(parents=True, exist_ok=True)
        det = LoopDetector(self.detector_conf, K=K, database=folder / "keyframes.h5", descriptor=self.descriptor)
        robot = self.robots[name] = _Robot(det, K, self.conf["points_cache"])
        if det.db is None:
            return robot
        stored = self._stored_entries(det)
        robot.ids = [fid for fid, _ in stored]
        robot.unchecked = None if self._certified(robot) is not None else list(robot.ids)
        if stored:  # a shared memory may hold them already (another replica, a previous run): an upsert
            self.places.add(name, robot.ids, [entry for _, entry in stored])
        for fid, pose in zip(robot.ids, det.db.poses()):
            if np.isfinite(pose).all():
                robot.poses[fid] = Sim3.from_pose(pose).matrix()
        return robot

    def _save_camera(self, name: str) -> None:
        """Writes the robot's ``camera.json`` (its intrinsics) if it has none yet."""
        camera = self.root / name / "camera.json"
        if not camera.exists():
            K = self.robots[name].K
            write_text_atomic(camera, json.dumps({"format_version": CAMERA_FORMAT_VERSION,
                                                  "K": None if K is None else np.asarray(K).tolist()}))

    def check_retry(self, robot: str, keyframe: int, image: np.ndarray) -> None:
        """Refuses (``ConflictError``) a retry of a stored keyframe whose image differs from the stored one's."""
        r = self.robots.get(robot)
        if r is None or isinstance(r.detector, _Adopted) or r.detector.db is None:
            return
        stored = next((e.fingerprint for e in r.detector.db.frames() if e.frame_id == keyframe), "")
        if stored and stored != _image_fingerprint(image):
            raise ConflictError(f"robot {robot!r} sent keyframe {keyframe} before, with another image")

    def export(self, robot: str, keyframes: list[int] | None = None) -> list[tuple[int, SharedKeyframe]]:
        """The robot's keyframes (all, or those of ``keyframes`` in the place memory) as ``adopt`` takes them: the
        local features of the latest ``adopted_features`` only (``None`` for the others: ``features`` on demand), the
        searched entries only when the place memory is not shared (``None``: every worker searches them there)."""
        r = self.robots[robot]
        ids = sorted(k for k in (r.ids if keyframes is None else set(keyframes) & set(r.ids)) if k in r.poses)
        entries = {} if self.places.shared else self._entries(r, ids)
        with_features = set(ids[-self.conf["adopted_features"]:])
        certified = self._certified(r)
        return [(k, SharedKeyframe(entries.get(k), r.detector.keyframe_features(k) if k in with_features else None,
                                   r.poses[k], r.K, certified)) for k in ids]

    def _entries(self, r: _Robot, ids: list[int]) -> dict[int, np.ndarray]:
        """The place-memory entries of the robot's keyframes ``ids``: the one just processed kept, the others read
        back from its database."""
        if r.last is not None and ids == [r.last[0]]:
            return dict([r.last])
        return dict(self._stored_entries(r.detector, set(ids)))

    def _stored_entries(self, det: LoopDetector, wanted: set[int] | None = None) -> list[tuple[int, np.ndarray]]:
        """``[(keyframe, entry)]`` of a detector's stored keyframes (those in ``wanted``, or all), in frame order,
        each in the place memory's own space as ``process`` made it: where the detector calibrates online its store
        keeps raw codes (``LoopDetector.calibrates_online``), made into the memory's entries here; else the searched
        entries (the weights' whitening: the memory's own)."""
        if det.db is None:
            return []
        raw = det.calibrates_online
        return [(fid, self.places.entry(code) if raw else code) for fid, code, _, _ in
                det.db.search_entries(features=False) if wanted is None or fid in wanted]

    def features(self, robot: str, keyframes: list[int]) -> list[Any]:
        """The local features of keyframes of a robot this recognizer owns (another one's ``fetch``)."""
        return self._features(robot, keyframes)

    def owned(self) -> list[str]:
        """The robots this recognizer runs the detector of (not adopted from another)."""
        return [name for name, r in self.robots.items() if not isinstance(r.detector, _Adopted)]

    def adopt(self, robot: str, shared: list[tuple[int, SharedKeyframe]]) -> None:
        """Adds another recognizer's keyframes of ``robot`` (``export``) to the robots matched across; a robot this
        recognizer owns is left alone."""
        r = self.robots.get(robot)
        if r is None:
            fetch = None if self.fetch is None else functools.partial(self.fetch, robot)
            r = self.robots[robot] = _Robot(_Adopted(self.conf["adopted_features"], fetch),  # type: ignore[arg-type]
                                            shared[0][1].K if shared else None)
        if not isinstance(r.detector, _Adopted):
            return
        if shared:
            r.detector.certified = shared[-1][1].certified  # its owner's calibration as of its newest keyframe
        for keyframe, kf in shared:
            if keyframe not in r.poses:
                if kf.features is not None:
                    r.detector.remember(keyframe, kf.features)
                r.poses[keyframe] = kf.pose
                r.ids.append(keyframe)
                if kf.entry is not None:  # a memory of this process (a shared one holds it already)
                    self.places.add(robot, [keyframe], [kf.entry])

    parallel_robots = True  #: keyframes of different robots may be processed at the same time (see the class doc)

    def committed(self, robot: str) -> None:
        """The service stored the robot's latest keyframe. Nothing to do here: every robot lives in this one
        recognizer (``cae_lcd.fleet.workers.RayRecognizer`` shares it with its other workers now)."""

    def has(self, robot: str, keyframe: int) -> bool:
        """True when the robot's database already holds ``keyframe`` (or a later one)."""
        r = self.robots.get(robot)
        return r is not None and not isinstance(r.detector, _Adopted) and keyframe < r.detector.next_frame_id

    def check(self, robot: str, K: np.ndarray | None) -> None:
        """Refuses intrinsics that differ from the robot's first ones; changes nothing."""
        r = self.robots.get(robot)
        if r is not None and K is not None and (r.K is None or not np.allclose(r.K, K)):
            raise ConfigError(f"robot {robot}: intrinsics differ from its first keyframe's")

    def process(self, robot: str, keyframe: int, timestamp: float, pose: np.ndarray, image: np.ndarray,
                K: np.ndarray | None = None, depth: np.ndarray | None = None) -> Recognition:
        """Runs one keyframe through the robot's detector (stored in its database) and across the other robots.

        Args:
            robot: its name. keyframe: its id (after the robot's last). timestamp: seconds.
            pose: ``(4, 4)`` camera-to-map pose in the robot's map. image: ``(H, W[, C])`` image.
            K: ``(3, 3)`` intrinsics (the first keyframe's are kept). depth: ``(H, W)`` depth map, or None.

        Raises:
            ConfigError, ImageError: a bad input (also a depth map of a robot without intrinsics); nothing was stored.
        """
        check_image(image, "image")  # before a new robot's folder is made: a refused keyframe leaves nothing
        with self._lock:
            self.check(robot, K)
            r = self.robots.get(robot)
            if depth is not None and K is None and (r is None or r.K is None):  # it would be dropped without a word
                raise ConfigError(f"robot {robot}: a depth map needs intrinsics (with the robot's first keyframe)")
            if r is None or isinstance(r.detector, _Adopted):  # first keyframe here (adopted keyframes: now owned)
                r = self._open(robot, K)
        with r.lock:
            res = r.detector.process(image, frame_id=keyframe, timestamp=timestamp, pose=pose,
                                     fingerprint=_image_fingerprint(image))
        with self._lock:
            self._save_camera(robot)
            r.poses[keyframe] = np.asarray(pose, np.float64)
            if res.gated or res.code is None:
                return Recognition(gated=True)
            entry = self.places.entry(res.code)  # in the memory's one space (a detector's refit moves its own)
            r.ids.append(keyframe)
            r.last = (keyframe, entry)
            if depth is not None and r.K is not None:
                r.remember_points(keyframe, points_from_depth(self._features(robot, [keyframe])[0].keypoints,
                                                              depth, r.K))
            due = self._catch_up_due(robot, keyframe)  # {other: rule}: its earlier keyframes to match now
            chosen, rules = self._shortlist(robot, entry)
        caught = [(k, self._matched(robot, k, *self._shortlist(robot, e, due))) for k, e in
                  sorted(self._entries(r, r.unchecked or []).items())] if due else []
        matches = self._matched(robot, keyframe, chosen, rules)
        # delayed loops of earlier keyframes (a run, or a refit, certified them; the detector reports each once)
        delayed = [(cd.frame_id, q, self._verify_pair(robot, q, cd.frame_id)) for q, cd in res.confirmed]
        out = Recognition()
        with self._lock:
            if res.loop is not None:  # the detector's verification of the pair: not checked again
                self._add_edge(out, "loop", (robot, res.loop.frame_id), (robot, keyframe), res.verification)
            for ref, q, check in delayed:
                self._add_edge(out, "loop", (robot, ref), (robot, q), check)
            for k, (found, runs) in caught:  # in keyframe order, before this one: each pair's run goes on from them
                self._cross(out, robot, k, found, runs, among=due)
            if due:
                log.info("robot %s certified: %d earlier keyframes matched against %d robots (%d matches)", robot,
                         len(caught), len(due), sum(len(f) for _, (f, _) in caught))
                r.unchecked = None
            self._cross(out, robot, keyframe, *matches)
            self.places.add(robot, [keyframe], [entry])
        return out

    def _catch_up_due(self, robot: str, keyframe: int) -> dict[str, tuple[int, int]]:
        """The robots against which ``robot``'s earlier keyframes are matched now (their pair's rule, ``_cross_rule``):
        on the robot's first certified keyframe, every robot whose pair rule is then in force, the robot's
        keyframes before it (its warm-up, at most ``cross.catch_up`` newest) being those no rule could check. The
        other direction needs no second pass: another robot's keyframes from before it was certified are matched
        against this robot's by its own catch-up, its later ones by its own queries, so every pair of keyframes is
        checked once. Called under the lock; ``unchecked`` tracks the robot's keyframes until then."""
        r = self.robots[robot]
        if r.unchecked is None or not self._calibrated:
            return {}
        if self._certified(r) is None:
            r.unchecked.append(keyframe)
            return {}
        limit = self.conf["cross"]["catch_up"]  # this keyframe is not among them: it goes live
        r.unchecked = r.unchecked[-limit:] if limit else []
        due = {o: rule for o in self.robots if o != robot and (rule := self._cross_rule(r, self.robots[o]))}
        if not due or not r.unchecked:
            r.unchecked = None
            return {}
        return due

    def _shortlist(self, robot: str, entry: np.ndarray, among: dict[str, tuple[int, int]] | None = None
                   ) -> tuple[dict[str, np.ndarray], dict[str, tuple[int, int] | None]]:
        """The other robots' keyframes to verify against an entry of ``robot`` (the fleet memory's top
        ``cross.search_k``, at most ``cross.k`` a robot and ``cross.budget`` in all) and each pair's rule
        (``_cross_rule``; ``among``: only these robots, with these rules)."""
        c = self.conf["cross"]
        with self._lock:
            found = self._known(self.places.search(robot, entry, c["search_k"]))  # {other: (keyframes, scores)}
            if among is not None:
                found = {o: hits for o, hits in found.items() if o in among}
            chosen = shortlist({o: s for o, (_, s) in found.items()}, c["k"], c["min_score"], c["budget"])
            rules = {o: among[o] if among is not None else self._cross_rule(self.robots[robot], self.robots[o])
                     for o in chosen}  # (inliers, run) or None: no match
            return {o: found[o][0][top] for o, top in chosen.items()}, rules

    def _matched(self, robot: str, keyframe: int, candidates: dict[str, np.ndarray],
                 rules: dict[str, tuple[int, int] | None]) -> tuple[dict[str, tuple[int, Verification]], dict[str, int]]:
        """``robot``'s keyframe verified against each other robot's ``candidates``: its matches (``_best_match``)
        and the run each matched pair needs."""
        matches = {o: m for o, top in candidates.items() if (m := self._best_match(robot, keyframe, o, top, rules[o]))}
        return matches, {o: rules[o][1] for o in matches}  # type: ignore[index]

    def _known(self, found: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The search results of keyframes this recognizer has (a shared place memory may hold another worker's
        newest keyframe before the service stored it and this recognizer adopted it), best first."""
        out = {}
        for other, (keyframes, scores) in found.items():
            r = self.robots.get(other)
            keep = np.array([r is not None and k in r.poses for k in keyframes.tolist()], bool)
            if keep.any():
                out[other] = (keyframes[keep], scores[keep])
        return out

    def _cross(self, out: Recognition, robot: str, keyframe: int, matches: dict[str, tuple[int, Verification]],
               runs: dict[str, int], among: dict[str, Any] | None = None) -> None:
        """Updates the overlap rules with the keyframe's verified matches of other robots (``runs``: the consecutive
        matches each pair needs, ``_cross_rule``; ``among``: only the rules of these robots), adds edges."""
        accepted = self.tracker.update(robot, keyframe, {o: m[0] for o, m in matches.items()}, runs, among)
        keep = max([self.conf["overlap"]["required"], *runs.values()])
        for other, (match, check) in matches.items():
            recent = self._checks.setdefault((robot, other), {})
            recent[keyframe] = check
            for old in sorted(recent)[:-keep]:
                del recent[old]
            if other in accepted:  # the accepting run's matches, each an edge
                for kf, m in self.tracker.rules[(robot, other)].accepted or []:
                    if kf in recent:
                        self._add_edge(out, "overlap", (other, m), (robot, kf), recent[kf])
            elif self.tracker.accepted(robot, other):
                self._add_edge(out, "overlap", (other, match), (robot, keyframe), check)
            pair = frozenset((robot, other))
            rec = next((e for e in out.edges if e.kind == "overlap" and e.robot_a == other), None)
            if rec is not None and pair not in self._recorded:  # the first edge of an accepted overlap records it
                self._recorded.add(pair)
                out.overlaps.append(self._overlap_record(rec))

    def resume(self, overlaps: list[OverlapRecord], edges: list[EdgeRecord]) -> None:
        """Continues after a restart: overlaps already accepted (stored) stay accepted, and the overlap edges already
        stored count towards ``max_edges_per_pair``."""
        for o in overlaps:
            self._recorded.add(frozenset((o.robot_a, o.robot_b)))
            self.tracker.accept(o.robot_a, o.robot_b)
        for e in edges:
            if e.kind == "overlap":
                self._edges[(e.robot_a, e.robot_b)] = self._edges.get((e.robot_a, e.robot_b), 0) + 1

    def _best_match(self, robot: str, keyframe: int, other: str, top: np.ndarray,
                    rule: tuple[int, int] | None) -> tuple[int, Verification] | None:
        """Of the other robot's keyframes ``top`` (its shortlisted candidates), the one that verifies best against
        the query, if it has the inliers of the pair's ``rule`` (``_cross_rule``; None: no match counts, none is
        verified)."""
        if rule is None:
            return None
        q, o, c, need = self.robots[robot], self.robots[other], self.conf["cross"], rule[0]
        K = q.K if q.K is not None and o.K is not None and np.allclose(q.K, o.K) else None
        checks = q.detector.verifier.verify(self._features(robot, [keyframe])[0], self._features(other, top), K,
                                            c["min_matches"], need, False)
        best = max(range(len(top)), key=lambda j: (checks[j].inliers, checks[j].matches))
        if checks[best].inliers < max(need, 1):
            return None
        return int(top[best]), checks[best]

    def _cross_rule(self, q: _Robot, o: _Robot) -> tuple[int, int] | None:
        """``(inliers, run)``: what a match between two robots' keyframes needs, and the consecutive matches that
        accept their overlap (the module doc's rule). Calibrated, the stricter of the two robots'
        ``certified_match`` (the run at least ``overlap.required``; None while either has none: nothing counts);
        under the fixed policy ``(cross.min_inliers, overlap.required)``."""
        required = self.conf["overlap"]["required"]
        if not self._calibrated:
            return self.conf["cross"]["min_inliers"], required
        a, b = self._certified(q), self._certified(o)
        return None if a is None or b is None else (max(a[0], b[0]), max(a[1], b[1], required))

    def _certified(self, r: _Robot) -> tuple[int, int] | None:
        """The robot's ``certified_match`` now (an adopted robot's: as its owner last exported it)."""
        if isinstance(r.detector, _Adopted):
            return r.detector.certified
        return certified_match(r.detector.deciding_calibration, self.detector_conf["search"]["exclude_recent"])

    def _add_edge(self, out: Recognition, kind: str, a: tuple[str, int], b: tuple[str, int],
                  check: Verification | None) -> None:
        """Appends the edge ``a -> b`` (``node_a^-1 o node_b``) when its similarity can be estimated."""
        pair = (a[0], b[0])
        if kind == "overlap" and self._edges.get(pair, 0) >= self.conf["max_edges_per_pair"]:
            return
        if check is None:  # a loop the detector accepted without verifying it (``policy.verify: false``)
            check = self._verify_pair(b[0], b[1], a[1])
        pts_a, pts_b = self._points(a[0], a[1]), self._points(b[0], b[1])
        if pts_a is None or pts_b is None or check.inliers <= 0:
            return
        pairs = check.pairs[check.geometry.mask][:, ::-1]  # (feature in a, feature in b)
        found = estimate_overlap(pairs, pts_a, pts_b, self.conf["sim3"])
        if found is None or found[1].sum() < self.conf["min_points"]:
            log.debug("%s %s -> %s: no similarity from %d matches", kind, a, b, len(pairs))
            return
        self._edges[pair] = self._edges.get(pair, 0) + 1
        out.edges.append(EdgeRecord(kind, a[0], a[1], b[0], b[1], found[0], float(found[1].sum())))

    def _verify_pair(self, robot: str, query: int, ref: int) -> Verification:
        """The robot's detector's verification of its keyframe ``query`` against its keyframe ``ref`` (matches,
        geometry): a loop it reported without its check (a delayed one, or ``policy.verify: false``)."""
        fq, fr = self._features(robot, [query, ref])
        return self.robots[robot].detector.verifier.verify(fq, [fr], self.robots[robot].K)[0]

    def _points(self, robot: str, keyframe: int) -> np.ndarray | None:
        """``(N, 3)`` 3D points of the keyframe's features in its camera frame (cached), None without intrinsics."""
        r = self.robots[robot]
        if keyframe in r.points:
            r.points.move_to_end(keyframe)
            return r.points[keyframe]
        near = r.neighbour(keyframe)
        if r.K is None or near is None or keyframe not in r.poses or near not in r.poses:
            return None
        fk, fn = self._features(robot, [keyframe, near])
        return r.remember_points(keyframe, self.triangulator(fk, r.poses[keyframe], fn, r.poses[near], r.K))

    def _features(self, robot: str, keyframes: Any) -> list[Any]:
        """The keyframes' local features (``LoopDetector.keyframe_features``), read while the robot's detector is
        not processing a keyframe (its own thread may be)."""
        r = self.robots[robot]
        with r.lock:
            return [r.detector.keyframe_features(int(k)) for k in keyframes]

    def _overlap_record(self, edge: EdgeRecord) -> OverlapRecord:
        """The accepted overlap: the similarity mapping robot b's map into robot a's, from ``edge``."""
        pa = Sim3.from_pose(self.robots[edge.robot_a].poses[edge.keyframe_a])
        pb = Sim3.from_pose(self.robots[edge.robot_b].poses[edge.keyframe_b])
        T = pa.compose(edge.relative).compose(pb.inverse())
        log.info("overlap accepted: robot %s keyframe %d ~ robot %s keyframe %d (scale %.3f)", edge.robot_b,
                 edge.keyframe_b, edge.robot_a, edge.keyframe_a, T.s)
        return OverlapRecord(edge.robot_a, edge.robot_b, T, self.conf["overlap"]["required"], time.time())

    def forget(self, robot: str) -> None:
        """Starts the robot's recognition again from nothing (an admin's reset): its detector is closed, its folder
        moved aside to ``robots/.reset/NAME-TIME`` (kept for inspection), its entries taken out of the place memory
        and its pairs' overlap state forgotten; its next keyframe opens a new database. A quarantined robot is
        released."""
        with self._lock:
            r = self.robots.pop(robot, None)
            if r is not None and not isinstance(r.detector, _Adopted):
                with r.lock:
                    try:
                        r.detector.close()
                    except Exception as err:  # noqa: BLE001 -- a damaged database: moved aside all the same
                        log.warning("robot %s: its database did not close cleanly (%s)", robot, err)
            folder = self.root / robot
            if (self._owns is None or self._owns(robot)) and (folder.exists() or folder.is_symlink()):
                aside = self.root / ".reset" / f"{robot}-{time.strftime('%Y%m%dT%H%M%S')}-{time.time_ns() % 10**9}"
                aside.parent.mkdir(parents=True, exist_ok=True)
                folder.rename(aside)
            self.places.remove(robot)
            self.tracker.rules = {k: v for k, v in self.tracker.rules.items() if robot not in k}
            self._checks = {k: v for k, v in self._checks.items() if robot not in k}
            self._edges = {k: v for k, v in self._edges.items() if robot not in k}
            self._recorded = {p for p in self._recorded if robot not in p}
            self.quarantined.pop(robot, None)

    def close(self) -> None:
        """Flushes and closes every robot's database and the place memory."""
        for r in self.robots.values():
            r.detector.close()
        self.places.close()
