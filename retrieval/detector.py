"""The loop-closure detector: gate -> encode -> search -> verify -> decide -> insert, one frame at a time.

    >>> det = LoopDetector(K=K, database="run/keyframes.h5")       # doctest: +SKIP
    >>> res = det.process(image, frame_id=i, timestamp=t)            # doctest: +SKIP
    >>> res.loop                                                     # Candidate or None   # doctest: +SKIP

``process`` returns a ``FrameResult``:

    frame_id    int
    gated       bool          True when the quality gate rejected the frame (nothing else ran)
    edge_ratio  float         the gate's edge-pixel ratio
    candidates  list[Candidate]  top-k keyframes (recent ones excluded) with score, matches, inliers
    loop        Candidate | None  the accepted match, if any
    R, t        (3, 3), (3,)  relative pose of the loop (essential-matrix model only), else None
    ms          dict[str, float]  milliseconds by stage: gate, encode, features, search, verify, insert, total
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from cae.conf import ConfigError, merge_conf
from cae.preprocess import to_gray_u8, to_network_u8, to_uint8
from verify.features import FEATURES, Features, create_extractor
from verify.gate import EdgeGate
from verify.geometry import GeometricVerifier
from verify.verifier import VERIFIERS, Verification, create_verifier

from .database import FeatureStore, KeyframeDatabase, KeyframeRecord
from .descriptors import DESCRIPTORS, create_descriptor
from .index import INDEXES, KeyframeIndex

__all__ = ["Candidate", "FrameResult", "LoopDetector", "default_conf", "resolve_conf"]

log = logging.getLogger(__name__)

default_conf: dict[str, Any] = {
    "gate": EdgeGate.default_conf,  # image-quality gate (Canny edge ratio)
    "encoder": {"name": "cae"},  # global descriptor by registry name (cae; baselines) and its options
    "index": {"name": "flat"},  # code index by registry name (flat, fp16, sq8, hnsw) and its options
    "search": {
        "k": 10,  # candidates retrieved per query (paper: top-10)
        "exclude_recent": 50,  # frames younger than this many frames are not searched (paper: 9)
        "exclude_recent_s": None,  # also exclude frames younger than this many seconds (needs timestamps)
        "min_score": 0.0,  # candidates below this cosine similarity are not verified
    },
    "features": {"name": "sift"},  # local features by registry name and their options
    "matching": {"name": "ratio"},  # descriptor matcher by registry name and its options
    "geometry": GeometricVerifier.default_conf,  # RANSAC model and thresholds
    "policy": {
        "min_matches": 5,  # putative (ratio-test) matches a candidate needs (paper: 5)
        "min_inliers": 50,  # geometric inliers a candidate needs (0: none); chosen on KITTI, see BENCHMARKS.md
        "check_all": False,  # True: geometric check on every candidate; False: skip those that cannot win (same loops)
    },
    "runtime": {
        "threads": None,  # CPU threads for torch/OpenCV (halved for each side when parallel); None = all cores
        "parallel": False,  # features in a worker thread while the encoder runs (cores split); slower on 2 cores
        "flush_every": 1,  # flush the database every this many frames (1: a killed run loses nothing)
        "features": "memory",  # keyframe features for verification: "memory" (all), "database" (bounded memory)
        "feature_cache": 512,  # with features "database": keyframes' features kept in memory (LRU)
    },
}

_REGISTRY_SECTIONS = {"encoder": DESCRIPTORS, "index": INDEXES, "features": FEATURES, "matching": VERIFIERS}
_NOT_PERSISTED = ("runtime",)  # sections that may change between a run and its resumption


def resolve_conf(conf: dict[str, Any] | None = None) -> dict[str, Any]:
    """Merges a user conf onto ``default_conf``; a named unit's section merges onto that unit's own defaults.

    Raises:
        ConfigError: unknown key (named, with the allowed ones), or unknown unit name.
    """
    conf = conf or {}
    base = dict(default_conf)
    for section, registry in _REGISTRY_SECTIONS.items():
        user = conf.get(section) or {}
        name = user.get("name", default_conf[section]["name"]) if isinstance(user, dict) else None
        if name is not None:
            base[section] = registry.get(name).default_conf
    return merge_conf(base, conf)


@dataclass
class Candidate:
    frame_id: int  #: the keyframe retrieved
    score: float  #: cosine similarity of the codes
    matches: int = 0  #: putative matches after the ratio test
    inliers: int = 0  #: geometric inliers; -1 when the check did not run (the pair could not pass or win)

    def as_row(self) -> tuple[int, float, int, int]:
        return (self.frame_id, self.score, self.matches, self.inliers)


@dataclass
class FrameResult:
    frame_id: int
    gated: bool
    edge_ratio: float
    candidates: list[Candidate] = field(default_factory=list)
    loop: Candidate | None = None
    R: np.ndarray | None = field(default=None, repr=False)
    t: np.ndarray | None = field(default=None, repr=False)
    ms: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready view (the fleet server and logs use it)."""
        return {"frame_id": self.frame_id, "gated": self.gated, "edge_ratio": self.edge_ratio,
                "candidates": [c.__dict__ for c in self.candidates],
                "loop": None if self.loop is None else self.loop.__dict__,
                "R": None if self.R is None else self.R.tolist(), "t": None if self.t is None else self.t.tolist(),
                "ms": self.ms}


class LoopDetector:
    """Appearance-based loop-closure detection, streaming.

    Args:
        conf: overrides of ``default_conf`` (nested dict, e.g. from ``configs/default.yaml``).
        K: ``(3, 3)`` camera intrinsics; enables the essential-matrix check (``geometry.model: auto``).
        database: path of an HDF5 keyframe database to write (resumed if it exists), or None to keep
            keyframes in memory only.
        encoder: an already loaded ``cae.Encoder`` for the ``cae`` descriptor (skips loading its weights).
    """

    def __init__(self, conf: dict[str, Any] | None = None, K: np.ndarray | None = None,
                 database: str | Path | None = None, encoder: torch.nn.Module | None = None) -> None:
        self.conf = resolve_conf(conf)
        c = self.conf
        threads = c["runtime"]["threads"] or os.cpu_count() or 1
        if c["runtime"]["parallel"]:  # the feature worker and the encoder run at once: split the cores between them
            threads = max(1, threads // 2)
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)
        self.K = None if K is None else np.asarray(K, np.float64).reshape(3, 3)
        self.gate = EdgeGate(c["gate"])
        extra = {"encoder": encoder} if encoder is not None else {}
        self.descriptor = create_descriptor(c["encoder"], **extra)
        self.extractor = create_extractor(c["features"])
        self.verifier = create_verifier(c["matching"], c["geometry"])
        self.verifier.geometry.model_for(self.K)  # fail now, not at the first loop, if E is asked without K
        self.index = KeyframeIndex(self.descriptor.dim, c["index"], c["search"]["exclude_recent"], c["search"]["exclude_recent_s"])
        if c["runtime"]["features"] not in ("memory", "database"):
            raise ConfigError(f"runtime.features must be 'memory' or 'database'; got {c['runtime']['features']!r}")
        if c["runtime"]["features"] == "database" and database is None:
            raise ConfigError("runtime.features 'database' needs a keyframe database (database=... / --out)")
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="features") if c["runtime"]["parallel"] else None
        self._next_id = 0
        self.db: KeyframeDatabase | None = None
        if database is not None:
            persisted = {k: v for k, v in c.items() if k not in _NOT_PERSISTED}
            self.db = KeyframeDatabase(database, persisted, self.descriptor.identity, c["runtime"]["flush_every"])
        from_db = self.db if c["runtime"]["features"] == "database" else None
        self.features = FeatureStore(from_db, c["runtime"]["feature_cache"])
        if self.db is not None:
            self._load(self.db)

    def _load(self, db: KeyframeDatabase) -> None:
        n = 0
        for fid, code, timestamp in db.search_entries():
            self.index.add(fid, code, timestamp)
            if self.features.db is None:  # memory mode: everything back in memory
                self.features[fid] = db.features(fid)
            n += 1
        self._next_id = db.last_frame_id() + 1
        if n:
            log.info("resumed %s: %d keyframes, next frame %d", db.path, n, self._next_id)

    @property
    def next_frame_id(self) -> int:
        """The frame id ``process`` assigns when none is given (one past the last frame seen)."""
        return self._next_id

    def process(self, image: np.ndarray, frame_id: int | None = None, timestamp: float | None = None,
                pose: np.ndarray | None = None, source: str = "") -> FrameResult:
        """Runs one frame through the pipeline and inserts it as a keyframe if it passes the gate.

        Args:
            image: grey/BGR/BGRA, uint8/uint16/float, any size (as ``cv2.imread(..., IMREAD_UNCHANGED)`` gives).
            frame_id: increasing id; None = one past the previous frame.
            timestamp: seconds (used by ``search.exclude_recent_s`` and stored).
            pose: ``(3, 4)`` camera-to-world pose, stored with the keyframe when given.
            source: free text stored with the keyframe (e.g. the file name).
        """
        fid = self._next_id if frame_id is None else int(frame_id)
        if fid < self._next_id:
            raise ConfigError(f"frame id {fid} is not after the last frame processed ({self._next_id - 1})")
        self._next_id = fid + 1
        c = self.conf
        ms: dict[str, float] = {}
        t_start = t0 = time.perf_counter()
        image8 = to_uint8(image)  # once: 16-bit and float frames are scanned and scaled here only
        gray = to_gray_u8(image8)
        net = to_network_u8(image8)  # one resize serves the gate and the encoder
        is_grey = image.ndim == 2 or image.shape[2] == 1  # then the three channels are equal
        gate = self.gate(net[:, :, 0] if is_grey else cv2.cvtColor(net, cv2.COLOR_RGB2GRAY))
        ms["gate"] = (time.perf_counter() - t0) * 1e3
        if not gate.passed:
            if self.db is not None:
                self.db.add_gated(fid)
            ms["total"] = (time.perf_counter() - t_start) * 1e3
            return FrameResult(fid, True, gate.edge_ratio, ms=ms)

        # local features: first when the descriptor needs them, else in the worker thread (parallel) or after search
        feats, pending = None, None
        if self.descriptor.needs_features:
            feats, ms["features"] = self._timed_extract(gray)
        elif self._pool is not None:
            pending = self._pool.submit(self._timed_extract, gray)
        t0 = time.perf_counter()
        code = self.descriptor(image, feats, network_image=net)
        ms["encode"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        scores, ids = self.index.search(code, fid, c["search"]["k"], timestamp)
        keep = scores >= c["search"]["min_score"]
        candidates = [Candidate(int(i), float(s)) for s, i in zip(scores[keep], ids[keep])]
        ms["search"] = (time.perf_counter() - t0) * 1e3
        if feats is None:
            t0 = time.perf_counter()
            feats, ms["features"] = pending.result() if pending is not None else self._timed_extract(gray)
            ms["features_wait"] = (time.perf_counter() - t0) * 1e3  # what the frame waited for them

        t0 = time.perf_counter()
        checks = self.verifier.verify(feats, [self.features[cd.frame_id] for cd in candidates], self.K,
                                      c["policy"]["min_matches"], c["policy"]["min_inliers"], c["policy"]["check_all"])
        for cand, check in zip(candidates, checks):
            cand.matches, cand.inliers = check.matches, check.inliers
        loop, best = self._decide(candidates, checks)
        ms["verify"] = (time.perf_counter() - t0) * 1e3

        t0 = time.perf_counter()
        self.index.add(fid, code, timestamp)
        if self.db is not None:
            self.db.append(KeyframeRecord(fid, code, feats, timestamp, pose, source, gate.edge_ratio,
                                          np.array([cd.as_row() for cd in candidates], np.float64).reshape(-1, 4),
                                          -1 if loop is None else loop.frame_id))
        self.features[fid] = feats  # after the database has it: database mode may read it back from there
        ms["insert"] = (time.perf_counter() - t0) * 1e3
        ms["total"] = (time.perf_counter() - t_start) * 1e3
        geo = best.geometry if best is not None else None
        return FrameResult(fid, False, gate.edge_ratio, candidates, loop, getattr(geo, "R", None),
                           getattr(geo, "t", None), ms)

    def _timed_extract(self, gray: np.ndarray) -> tuple[Features, float]:
        t0 = time.perf_counter()
        feats = self.extractor.extract(gray)
        return feats, (time.perf_counter() - t0) * 1e3

    def _decide(self, candidates: list[Candidate],
                checks: list[Verification]) -> tuple[Candidate | None, Verification | None]:
        """The accepted candidate: passes every policy threshold; most inliers, then most matches, then score."""
        p = self.conf["policy"]
        passing = [(cd, ch) for cd, ch in zip(candidates, checks)
                   if cd.matches >= p["min_matches"] and cd.inliers >= p["min_inliers"]]
        if not passing:
            return None, None
        return max(passing, key=lambda pair: (pair[0].inliers, pair[0].matches, pair[0].score))

    def close(self) -> None:
        """Flushes and closes the database and stops the worker thread."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self.db is not None:
            self.db.close()

    def __enter__(self) -> "LoopDetector":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
