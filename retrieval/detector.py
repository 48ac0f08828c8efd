"""The loop-closure detector: gate -> describe -> search -> temporal filter -> verify -> decide -> insert, one frame
at a time. How a frame is described and searched is the global descriptor's (``descriptor``: the CAE code by
default, searched by cosine; MILD's ORB descriptors, searched by multi-index hashing: ``retrieval.places``).

    >>> det = LoopDetector(K=K)   # in memory: the stream calibrates itself (retrieval.online)   # doctest: +SKIP
    >>> res = det.process(image, frame_id=i, timestamp=t)            # doctest: +SKIP
    >>> res.loop                                                     # Candidate or None   # doctest: +SKIP

``process`` returns a ``FrameResult``:

    frame_id    int
    gated       bool          True when the quality gate rejected the frame (nothing else ran)
    edge_ratio  float         the gate's edge-pixel ratio
    candidates  list[Candidate]  top-k hypotheses (recent keyframes excluded; and the one a stop carries the frame
                                 before's loop to, ``Decision.carry_to``) with score, seq_score, matches, inliers
                                 and confidence
    loop        Candidate | None  the accepted match, if any
    confirmed   list[(int, Candidate)]  delayed loops (calibrated, verified): the run of consecutive frames on one
                                 offset that accepted ``loop`` certifies its earlier members; ``(earlier frame_id,
                                 its keyframe)`` for each that was not a loop yet (reported once, with the run's
                                 confidence; their candidates were in those frames' results)
    R, t        (3, 3), (3,)  relative pose of the loop (essential-matrix model only), else None
    ms          dict[str, float]  milliseconds by stage: gate, encode, features, search, verify, insert, total;
                                 online (``retrieval.online``) also calibrate: recording the frame, checks, refits
    entry       (d,) | None   the searched entry (in the run's current code space: online, a refit moves it)
    code        (D,) | None   the frame's raw global code (online: float16-rounded, as its store keeps it); a
                                 memory of its own in a fixed whitening (the fleet's) makes its entries from it
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np
import torch

from cae.whitening import DEFAULT_DIM, DEFAULT_SHRINK
from cae_lcd.core.checks import check_frame_id, check_intrinsics, check_pose, check_timestamp
from cae_lcd.core.conf import Bool, Choice, ConfigError, Float, Floats, Int, check_conf, merge_conf
from cae_lcd.core.errors import DatabaseError
from cae_lcd.core.images import check_image, to_gray_u8, to_uint8
from cae_lcd.core.threads import BesideExecutor, apply_thread_policy, side_by_side
from verify.features import FEATURES, FeatureExtractor, Features, create_extractor
from verify.gate import EdgeGate
from verify.geometry import GeometricVerifier, GeometryResult
from verify.verifier import MATCHERS, Verification, create_verifier

from .decision import Confirmations, Decision, Stops
from .database import CANDIDATE_ROW, FeatureStore, KeyframeDatabase, KeyframeRecord
from .calibrate import Calibration, calibrated_features
from .descriptors import DESCRIPTORS, GlobalDescriptor, create_descriptor
from .feature_jobs import FeatureJobs, grey_copy, read_grey_copy
from .index import INDEXES
from .localise import Localiser
from .online import DRIFT_Z, OnlineCalibration, Seen
from .places import create_places
from .temporal import FILTERS, PAIR_CHUNK, CodeTable, SimilaritySource, TemporalFilter, create_filter

__all__ = ["Candidate", "FrameResult", "LoopDetector", "weights_whitening", "STAGES", "default_conf", "conf_rules",
           "resolve_conf"]

log = logging.getLogger(__name__)

MAX_PREFETCHED = 8  #: frames ``LoopDetector.prefetch_features`` holds at most (their images and extraction jobs)
LATE_BATCH = 256  #: pairs verified late at a refit at a time (``LoopDetector._verify_late``: their features held)
#: verified pairs with a pose (an essential matrix) whose two-view geometry ``detect`` has its detector keep
#: (``LoopDetector(kept_geometries=...)``, the oldest dropped first), so that a loop's edge reuses its check
#: (``LoopDetector.verified_geometry``): ~6 kB a pair (its inliers' points), ~25 MB at most; KITTI 90 checks 200
KEPT_GEOMETRIES = 4096
ADJACENT_SCAN = 8  #: ids ``LoopDetector._adjacent`` looks through for the next keyframe (gated frames skipped)
REPLAY_COPY_BYTES = 64 << 20  #: a refit's replay copies the keyframes' codes up to this size (``_replay_source``)
STAGES = ("gate", "encode", "features", "search", "filter", "verify", "insert", "total")  #: keys of ``FrameResult.ms``

default_conf: dict[str, Any] = {
    "gate": EdgeGate.default_conf,  # image-quality gate (Canny edge ratio)
    "descriptor": {"name": "cae"},  # global descriptor by registry name (cae; thumbnail, bovw; mild) and its options
    "whitening": {
        "enabled": True,  # False: the paper's raw cosine on the 4096-d code
        "source": "auto",  # "auto": fitted on the sequence when calibrating, else the weights' own (if any);
        #                    "sequence": the sequence's only; "weights": the one saved with the weights only
        "dim": DEFAULT_DIM,  # length of the whitened code (at most a quarter of the fitting codes)
        "shrink": DEFAULT_SHRINK,  # added to each component's variance, times their mean (regularises small sets)
        "skip_still": True,  # fitted on the sequence: leave out frames whose code did not change (camera still: one
        #                     place, weighed once, not as often as the robot waited there)
        "stream_fit": None,  # uncalibrated and no whitening from the weights: fit one on the stream's own first
        #                      this many keyframes (raw codes searched until then), then search the whitened codes
        #                      (index and table rebuilt once): a long stream's cost and memory stay small; None: raw
        #                      codes (the fleet compares its robots' entries in the raw space: leave it None there)
    },
    "index": {"name": "auto"},  # code index by registry name (auto, flat, fp16, sq8, hnsw, ivfpq) and its options
    "temporal": {"name": "sequence"},  # temporal-consistency filter by registry name (sequence, none, bayes)
    "search": {
        "k": 10,  # candidates retrieved per query (paper: top-10)
        "exclude_recent": 50,  # frames younger than this many frames are not searched (paper: 9)
        "exclude_recent_s": None,  # also exclude frames younger than this many seconds (needs timestamps)
        "min_score": 0.0,  # candidates below this cosine similarity are not verified
        "verify_min_z": 3.0,  # calibrated: a candidate whose temporal and single-frame scores are both under the
        #                       far-side null's median + this many sigmas (no evidence beyond chance) is not
        #                       verified: a frame with no other candidate needs no local features; None: verify all
        "localise_steps": 16,  # keyframes an accepted loop's walk along the map verifies at most, toward where the
        #                        matched features' scale change says the query stands (``retrieval.localise``: a
        #                        revisit at another speed accepts keyframes metres behind); 0: the loop names the
        #                        keyframe accepted
    },
    "features": {"name": "sift"},  # local features by registry name and their options
    "matcher": {"name": "ratio"},  # descriptor matcher by registry name and its options
    "geometry": GeometricVerifier.default_conf,  # RANSAC model and thresholds
    "calibration": {
        "enabled": True,  # calibrate thresholds on the sequence (detect) / on the stream itself or use the
        #                   calibration given (API, ``online``); False: the fixed policy below
        "online": True,  # calibrate on the stream itself as it grows (``retrieval.online``: a warm-up of 2 exclusion
        #                  windows accepting nothing, refits at doublings, a calibration given checked against the
        #                  stream first; with a store, its state is kept there and a resumed run goes on with it):
        #                  the API, ``detect`` (the same algorithm) and the fleet's robots; False: the decision is
        #                  fixed for the run: ``detect`` calibrates on a look-ahead pass over the whole sequence first
        #                  (``--lookahead``), the API uses the calibration given, or without one the fixed policy
        "expected_false_loops": 0.1,  # a-contrario target: expected false loops over the whole run
        "null_pairs": 1200,  # pairs verified with local features for the nulls (hard-negative sequences: the
        #                     pair null is their empirical p-value, so more pairs let one pair claim more)
        "min_features": 50,  # median keypoints per frame under which local verification is not used
        "min_inliers": 12,  # floor of the calibrated inlier threshold (a 7-point model always fits 7)
        "speeds": [1.0, 2.0, 3.0],  # keyframes the map advances per query frame on the line of a verified run
        #                            (retrieval.decision: a run is fused on the line of one speed, their choice
        #                            counted in the tests): a revisit 2x or 3x as fast as the map is fused frame
        #                            after frame; a speed between them, or a slower one to 0.5x, stays within a
        #                            line's drift (TOL)
        "score_speeds": [0.87, 1.0, 1.15],  # the same for the score path's windows (too few local features to
        #                         verify: a 64x32 camera, a night), which need the speed itself (a window of 10
        #                         frames at 1.25x is 2.5 frames off a 1x line): the map's pace and 15 % either
        #                         side (a walk or a drive again at another pace; KITTI 90 at 64x32, its second
        #                         pass at 1.15x: 0 -> 86 of 87 found, at 1.25x 61 of 80). A line at another speed
        #                         does not read through a stop (``ScoreSpans``' ``stops``). Each speed is
        #                         counted in the tests: weak codes lose recall at the map's speed (Nordland's
        #                         darkened winter 0.928 with [1.0] -> 0.902; slower lines cost more: [0.8, 1,
        #                         1.25] 0.754); [1.0, 2.0, 3.0] finds KITTI 90's second pass at 2x, 64x32 (49/50)
        "verification": "auto",  # "auto": used when features suffice; "on": always; "off": global + temporal only
        "max_frames": 2000,  # frames the calibration reads at most (blocks spread over longer sequences)
        "features_px": 384,  # calibrated: local features downscaled to this longer side (px) instead of
        #                      features.resize_max (which the fixed policy keeps: its min_inliers was chosen at 512;
        #                      an extractor at full resolution stays so), the calibration's and the run's: 0.6x the
        #                      time of 512 px with the same precision and recall on every shared set (BENCHMARKS.md,
        #                      issue 18); None: features.resize_max
    },
    "policy": {  # the acceptance rule when not calibrated (calibration.enabled: false, or no calibration given)
        "verify": True,  # check candidates with local features and geometry; False: the scores alone decide (MILD)
        "min_matches": 5,  # putative (ratio-test) matches a candidate needs (paper: 5)
        "min_inliers": 50,  # uncalibrated: geometric inliers a candidate needs (0: none); chosen on KITTI
        "min_seq_score": None,  # uncalibrated: the temporal filter's score a candidate needs (MILD: posterior 0.7)
        "check_all": False,  # True: geometric check on every candidate; False: skip those that cannot win (same loops)
        "still_cos": 0.999,  # uncalibrated: the frames of the query's stop (each stored frame's code unchanged from
        #                     the one before: cosine >= this; ``retrieval.decision.Stops``) count as one for
        #                     search.exclude_recent: a robot standing or creeping is not back at a place (adjacent
        #                     moving frames: <= 0.995 on KITTI, where the rule changes nothing; standing: >= 0.9999);
        #                     None: off (the paper's literal rule)
    },
    "runtime": {
        "threads": 1,  # threads of each library's pool (torch, OpenCV, faiss: ``cae_lcd.core.threads``); 1 = the cores go to
        #                the pipeline's own workers (``detect`` reads and encodes ahead), which a busy neighbour
        #                process slows but cannot stall; None = all cores
        "lazy_features": True,  # local features only for frames that verify a candidate (extracted when needed,
        #                         then cached); False: on every frame as it arrives (the same results, slower)
        "feature_worker": True,  # a worker thread extracts local features beside the main thread: a frame's own
        #                          while it is encoded (every frame when not lazy; lazy, when the frame before
        #                          needed its own: a revisit under way), and the keyframes after a frame's verified
        #                          candidates (the next frames' likely candidates) once it has verified, and
        #                          online every keyframe of the warm-up (the first fit verifies pairs across all
        #                          of them: retrieval.online); the main thread runs a job itself when the worker
        #                          has not started it. The same features
        #                          either way. On a quiet 2-core machine one frame at a time through the API takes
        #                          27 ms with it, 37 without; on 2 cores fully taken by other work it lost
        #                          (BENCHMARKS.md, issue 18): off there
        "verify_worker": True,  # a second thread verifies beside the main one: half of a frame's matching, and the
        #                         geometric checks of its candidates taken in turn, and a refit's late checks
        #                         (OpenCV and torch release the GIL; the same results: ``Verifier.verify``)
        "flush_every": 256,  # frames moved from the database's write-ahead log into its columns at a time (each
        #                    frame is logged as it is stored: a killed run loses nothing whatever this is)
        "features": "memory",  # keyframe features for verification: "memory" (all), "database" (bounded memory);
        #                    "image": as "database", but a keyframe whose features were not needed when it came
        #                    (lazy) keeps a small grey copy (at the extractor's resolution) in the store instead,
        #                    and its features are extracted from it when a later query needs them: a stream's
        #                    store stays small where it does not revisit (without a store: "memory")
        "image_quality": 90,  # features "image": JPEG quality of the stored grey copy (the frame's own features are
        #                       extracted from the same copy); None: lossless PNG (about twice the bytes)
        "feature_cache": 512,  # keyframes' features kept in memory (LRU): with features "database", and those
        #                        extracted late (lazy_features) in either mode
    },
}

#: type and range of the detector's own sections (the units' sections are checked with their own ``conf_rules``)
conf_rules: dict[str, Any] = {
    "search": {"k": Int(1, 10_000), "exclude_recent": Int(0), "exclude_recent_s": Float(0, optional=True),
               "min_score": Float(-1, 1), "verify_min_z": Float(-100, 100, optional=True),
               "localise_steps": Int(0, 1000)},
    "policy": {"verify": Bool(), "min_matches": Int(0), "min_inliers": Int(0),
               "min_seq_score": Float(-1e9, 1e9, optional=True), "check_all": Bool(),
               "still_cos": Float(0, 1, lo_open=True, optional=True)},
    "whitening": {"enabled": Bool(), "source": Choice("auto", "sequence", "weights"), "dim": Int(1, 4096),
                  "shrink": Float(0, 100), "skip_still": Bool(), "stream_fit": Int(32, optional=True)},
    "calibration": {"enabled": Bool(), "online": Bool(), "expected_false_loops": Float(0, 100, lo_open=True),
                    "null_pairs": Int(10, 100_000), "min_features": Int(0), "min_inliers": Int(8),
                    "speeds": Floats(0.1, 10), "score_speeds": Floats(0.1, 10),
                    "verification": Choice("auto", "on", "off"), "max_frames": Int(100),
                    "features_px": Int(16, optional=True)},
    "runtime": {"threads": Int(1, 1024, optional=True), "lazy_features": Bool(), "feature_worker": Bool(),
                "verify_worker": Bool(), "flush_every": Int(1), "features": Choice("memory", "database", "image"),
                "image_quality": Int(1, 100, optional=True), "feature_cache": Int(1)},
}

_UNIT_SECTIONS = {"descriptor": DESCRIPTORS, "index": INDEXES, "features": FEATURES, "matcher": MATCHERS,
                  "temporal": FILTERS}
_FIXED_SECTIONS = {"gate": EdgeGate, "geometry": GeometricVerifier}
_NOT_PERSISTED = ("runtime",)  # sections that may change between a run and its resumption


def resolve_conf(conf: dict[str, Any] | None = None) -> dict[str, Any]:
    """Merges a user conf onto ``default_conf`` and checks every value; nothing is created or written.

    A named unit's section (``descriptor``, ``index``, ``temporal``, ``features``, ``matcher``) merges onto that unit's
    own defaults and is checked against its ``conf_rules``.

    Raises:
        ConfigError: unknown key (named, with the allowed ones), unknown unit name, or a value of the wrong type or
            out of range (named, with what is allowed).
    """
    if conf is not None and not isinstance(conf, dict):
        raise ConfigError(f"the configuration must be a mapping; got {type(conf).__name__}")
    conf = dict(conf or {})
    base = dict(default_conf)
    units: dict[str, Any] = dict(_FIXED_SECTIONS)
    for section, registry in _UNIT_SECTIONS.items():
        user = conf.get(section) or {}
        if not isinstance(user, dict):
            raise ConfigError(f"config section '{section}' must be a mapping, got {type(user).__name__}")
        units[section] = registry.get(user.get("name", default_conf[section]["name"]))
        base[section] = units[section].default_conf
    resolved = merge_conf(base, conf)
    check_conf(resolved, {**conf_rules, **{s: unit.conf_rules for s, unit in units.items()}})
    for section, unit in units.items():  # what one value's rule cannot say (values that must agree)
        if hasattr(unit, "check_section"):
            unit.check_section(resolved[section])
    if resolved["calibration"]["enabled"] and units["descriptor"].searched_by != "cosine":
        raise ConfigError(f"calibration.enabled needs a descriptor compared by cosine; "
                          f"'{resolved['descriptor']['name']}' is compared by {units['descriptor'].searched_by}: set "
                          "calibration.enabled: false (the fixed policy; --method mild does)")
    return resolved


def weights_whitening(conf: dict[str, Any], descriptor: GlobalDescriptor) -> Any:
    """The whitening an uncalibrated detector applies to ``descriptor``'s codes: the descriptor's own (its weights'),
    when ``whitening.enabled`` and its source is not the sequence; else None."""
    w = conf["whitening"]
    return getattr(descriptor, "whitening", None) if w["enabled"] and w["source"] != "sequence" else None


@dataclass
class Candidate:
    frame_id: int  #: the keyframe (a hypothesis of the temporal filter)
    score: float  #: single-frame cosine similarity of the (normalised) codes
    matches: int = 0  #: putative matches after the ratio test
    inliers: int = 0  #: geometric inliers; -1 when the check did not run (could not pass or win, or no verification)
    seq_score: float = 0.0  #: the temporal filter's score (equals ``score`` with ``temporal.name: none``)
    confidence: float = 0.0  #: what the acceptance rule thresholds: -log10 NFA when calibrated, else inliers
    #                            (the temporal score when the policy does not verify)

    def as_row(self) -> tuple[int, float, int, int, float, float]:
        """The stored candidate row, in ``retrieval.database.CANDIDATE_ROW`` order."""
        return (self.frame_id, self.score, self.matches, self.inliers, self.seq_score, self.confidence)


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
    entry: np.ndarray | None = field(default=None, repr=False)  #: the searched entry (``places.entry``), None gated
    verification: Verification | None = field(default=None, repr=False)  #: the loop's check: matches, transform
    confirmed: list[tuple[int, Candidate]] = field(default_factory=list)  #: delayed loops of earlier frames (above)
    code: np.ndarray | None = field(default=None, repr=False)  #: the raw global code (above), None gated

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready view (the fleet server and logs use it)."""
        return {"frame_id": self.frame_id, "gated": self.gated, "edge_ratio": self.edge_ratio,
                "candidates": [c.__dict__ for c in self.candidates],
                "loop": None if self.loop is None else self.loop.__dict__,
                "confirmed": [{"frame_id": q, "loop": c.__dict__} for q, c in self.confirmed],
                "R": None if self.R is None else self.R.tolist(), "t": None if self.t is None else self.t.tolist(),
                "ms": self.ms}


def _placed(best: tuple[Candidate, Any], passing: list[tuple[Candidate, Any]]) -> tuple[Candidate, Any]:
    """The calibrated loop among equals: ``best`` (the most confident, then most inliers, then the best window) or,
    where a keyframe one frame from it is as confident with as many inliers, the one whose own pair with the query
    is most alike (``score``). Evidence fused over a window saturates on a strong revisit, and lines one frame apart
    read nearly the same earlier frames: their windows do not say which frame the query is at, its own pair does.
    Where the reference's visit ends (joined to the next one) a line can run on into an unrelated keyframe whose
    window still reads the good pairs before it (``tests/retrieval/test_detector.py::TestWhereAVisitEnds``)."""
    cand = best[0]
    near = [pair for pair in passing if abs(pair[0].frame_id - cand.frame_id) <= 1
            and pair[0].confidence == cand.confidence and pair[0].inliers == cand.inliers]
    return max(near, key=lambda pair: (pair[0].score, pair[0].seq_score))


def _warn_uncertified_filter(filt: TemporalFilter) -> None:
    """Warns where a calibrated decision runs on a temporal filter whose promise it cannot certify: single frames,
    or lines at several speeds."""
    if filt.conf.get("length", 1) == 1:
        log.warning("temporal filter of single frames (temporal.name: %s): a calibrated decision's promise "
                    "(expected false loops over the run) is not certified without windows of several frames: "
                    "adjacent frames of a look-alike stretch are not independent (BENCHMARKS.md, 'Single frames "
                    "are not safe alone')", filt.conf.get("name", type(filt).__name__))
    if len([v for v in filt.conf.get("velocities", [1.0]) if v > 0]) > 1:
        log.warning("temporal filter lines at several speeds (temporal.velocities: %s): where local features are "
                    "too few to verify (the score path, a 64x32 camera) its windows are not placed within half a "
                    "window of the query's frame (KITTI 90 at 64x32 with [1, 2, 3]: precision 0.775); runs take "
                    "their speeds from calibration.speeds and calibration.score_speeds", filt.conf["velocities"])


class LoopDetector:
    """Appearance-based loop-closure detection, streaming.

    Args:
        conf: overrides of ``default_conf`` (nested dict, e.g. from ``configs/default.yaml``); checked in full before
            anything is created.
        K: ``(3, 3)`` camera intrinsics; enables the essential-matrix check (``geometry.model: auto``).
        database: path of an HDF5 keyframe database to write (resumed if it exists), or None to keep
            keyframes in memory only.
        encoder: an already loaded ``cae.Encoder`` for the ``cae`` descriptor (skips loading its weights).
        descriptor: an already built global descriptor (e.g. the one the calibration used), instead of building one
            from ``conf["descriptor"]``; its name must be the conf's.
        calibration: what ``retrieval.calibrate`` chose for this camera (gate reference, whitening, thresholds).
            None: with ``calibration.online``, the stream calibrates itself (``retrieval.online``; with a
            ``database``, its state is kept there and a resumed run goes on with it); else the fixed policy
            (``policy.min_inliers``), the weights' own whitening if they carry one. Given with
            ``calibration.online``: a prior, checked against the stream at the end of the warm-up (kept, or refitted
            on the stream); without: the run's fixed decision.
        frame_source: ``frame_source(frame_id) -> image`` gives a processed frame again (offline: read from its file)
            when its local features are needed after it was processed (``runtime.lazy_features``); None: a lossless
            PNG copy of the grey frame at the extractor's resolution is kept in memory instead.
        features: local features already extracted for some frames (``{frame_id: Features}``, e.g. by the
            calibration, from the same images): used instead of extracting them again.
        kept_geometries: the newest checks with a pose (an essential matrix) kept for ``verified_geometry``, at
            most (``detect`` keeps ``KEPT_GEOMETRIES`` for its loop edges); 0: none kept.

    Raises:
        ConfigError: a bad conf value, a K that is not a finite 3x3 matrix, or a database made with another conf.
        DatabaseError: the database is damaged, locked or cannot be written.
    """

    def __init__(self, conf: dict[str, Any] | None = None, K: np.ndarray | None = None,
                 database: str | Path | None = None, encoder: torch.nn.Module | None = None,
                 calibration: Calibration | None = None, descriptor: GlobalDescriptor | None = None,
                 frame_source: Callable[[int], np.ndarray] | None = None,
                 features: dict[int, Features] | None = None, kept_geometries: int = 0) -> None:
        self.conf = resolve_conf(conf)
        c = self.conf
        if isinstance(kept_geometries, bool) or not isinstance(kept_geometries, (int, np.integer)) \
                or kept_geometries < 0:
            raise ConfigError(f"kept_geometries must be an integer >= 0; got {kept_geometries!r}")
        self._kept_geometries = int(kept_geometries)
        self.K = None if K is None else check_intrinsics(K, "K")
        if c["runtime"]["features"] == "database" and database is None:
            raise ConfigError("runtime.features 'database' needs a keyframe database (database=... / --out)")
        if calibration is not None and not isinstance(calibration, Calibration):
            raise ConfigError("calibration must be a retrieval.calibrate.Calibration; got "
                              f"{type(calibration).__name__}")
        self.calibration = calibration if c["calibration"]["enabled"] else None
        online = c["calibration"]["enabled"] and c["calibration"]["online"] \
            and DESCRIPTORS.get(c["descriptor"]["name"]).searched_by == "cosine"
        self._online = OnlineCalibration(c, self.calibration) if online else None  # the stream calibrates itself
        self.gate = EdgeGate(c["gate"], None if self.calibration is None else self.calibration.edge_reference)
        if descriptor is not None and not isinstance(descriptor, DESCRIPTORS.get(c["descriptor"]["name"])):
            raise ConfigError(f"descriptor must be a {c['descriptor']['name']!r} descriptor (the conf's); got "
                              f"{type(descriptor).__name__}")
        self.descriptor = descriptor if descriptor is not None else \
            create_descriptor(c["descriptor"], **({"encoder": encoder} if encoder is not None else {}))
        self.whitening = self.calibration.whitening if self.calibration is not None else \
            weights_whitening(c, self.descriptor)
        if self.whitening is not None and self.whitening.input_dim != self.descriptor.dim:
            raise ConfigError(f"the whitening expects {self.whitening.input_dim}-d codes; the descriptor gives "
                              f"{self.descriptor.dim}-d ones")
        fconf = c["features"] if self.calibration is None and self._online is None else calibrated_features(c)
        if self.calibration is not None and self.calibration.features and self.calibration.features != fconf:
            raise ConfigError(f"the calibration was made on local features {self.calibration.features}; this run "
                              f"extracts {fconf} (features, calibration.features_px): calibrate again")
        self.extractor = create_extractor(fconf)
        self.verifier = create_verifier(c["matcher"], c["geometry"])
        self.verifier.geometry.model_for(self.K)  # fail now, not at the first loop, if E is asked without K
        stream_fit = c["whitening"]["stream_fit"] if self.whitening is None and c["whitening"]["enabled"] \
            and self.descriptor.searched_by == "cosine" else None
        self.places = create_places(self.descriptor, self.whitening, c, stream_fit)
        self.filter = create_filter(c["temporal"])
        if c["calibration"]["enabled"]:
            _warn_uncertified_filter(self.filter)
        self._init_decision()
        apply_thread_policy(c["runtime"]["threads"])
        self._init_lazy(database is not None, frame_source, features)
        self._next_id = 0
        self._closed = False
        self.db: KeyframeDatabase | None = None
        if database is not None:  # last: everything above can refuse the conf before a file is created
            persisted = {k: v for k, v in c.items() if k not in _NOT_PERSISTED}
            identity = self.descriptor.identity + ("" if self.calibration is None else
                                                   " calibration " + self.calibration.identity())
            self.db = KeyframeDatabase(database, persisted, identity, c["runtime"]["flush_every"])
        self._init_workers(fconf, online)
        #: ``prefetch_features``' frames: id -> (the image given, as uint8, grey, its prepared image once)
        self._ahead: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, Callable[[], Any]]] = {}
        self._delayed: dict[int, tuple[int, float]] = {}  # online: delayed loops reported, {frame: (keyframe, conf)}
        self._refitted: bool | None = None  # online: this keyframe's step adopted a decision (True: and rewhitened)
        self.features = FeatureStore(self.db if c["runtime"]["features"] in ("database", "image") else None,
                                     c["runtime"]["feature_cache"])  # features kept (not ``_unextracted``)
        if self.db is not None:
            try:
                self._load(self.db)
            except BaseException:
                self.close()
                raise

    def _init_workers(self, fconf: dict[str, Any], online: bool) -> None:
        """The threads beside the caller's (the feature worker extracting ``fconf``'s local features, the verify
        worker), where anything is verified (or will be: ``online``), and the walk that names a loop's keyframe."""
        c, verifies = self.conf, self._verify or online
        self._jobs = FeatureJobs(functools.partial(create_extractor, fconf), c["runtime"]["feature_cache"]) \
            if c["runtime"]["feature_worker"] and verifies and not self.descriptor.needs_features else None
        self._pool = BesideExecutor(thread_name_prefix="verify") if c["runtime"]["verify_worker"] and verifies else None
        self._wanted = False  # whether the previous frame's query needed its local features
        self._localiser = Localiser(self._verify_pair, self._features_of, max_steps=c["search"]["localise_steps"]) \
            if c["search"]["localise_steps"] else None  # an accepted loop named where the query is (the floor: _decide)

    def _init_decision(self) -> None:
        """What decides: whether candidates are verified, the inlier floor, the calibrated decision and its delayed
        loops (``retrieval.decision``), or, uncalibrated, the stop rule."""
        c = self.conf
        self._verify = bool(self.calibration.inlier_null) if self.calibration is not None else c["policy"]["verify"]
        self._verify = self._verify and self._online is None  # online: nothing verified until calibrated
        self._min_inliers = c["policy"]["min_inliers"]
        self.decision = None  # calibrated: the fused decision and the "too recent" rule (retrieval.decision)
        if self.calibration is not None:
            self.decision = self.calibration.decision(c["search"]["exclude_recent"], self.filter)
            self._min_inliers = int(self.decision.floor)  # weaker pairs still add fused evidence
        self._confirm = Confirmations(self.decision.reach) \
            if self.decision is not None and self.decision.confirms else None  # delayed loops
        still = c["policy"]["still_cos"]  # uncalibrated: the stop a still camera has not left is too recent
        self._still = Stops(still) \
            if self.decision is None and still is not None and self.descriptor.searched_by == "cosine" else None

    def _init_lazy(self, has_database: bool, frame_source: Callable[[int], np.ndarray] | None,
                   features: dict[int, Features] | None) -> None:
        """The state of late feature extraction (``runtime.lazy_features``)."""
        c, rt = self.conf, self.conf["runtime"]
        # a keyframe store keeps a grey copy of each keyframe whose features were not needed (runtime.features "image")
        self._keep_image = has_database and frame_source is None and rt["features"] == "image" and \
            rt["lazy_features"] and not self.descriptor.needs_features
        # lazy only where a frame can be had again after a restart: in memory, with a frame_source or its stored copy
        self._lazy = rt["lazy_features"] and not self.descriptor.needs_features \
            and (not has_database or frame_source is not None or self._keep_image)
        self._frame_source = frame_source
        # local features go into the database only where they cannot be had again from the frame's source (or are
        # read back from there: features "database", "image"); offline, its files give them again
        self._store_features = frame_source is None or rt["features"] in ("database", "image")
        self._given: dict[int, Features] = dict(features or {})  # frame -> features extracted before (calibration)
        self._unextracted: set[int] = set()  # keyframes whose features are not kept: extracted again when needed
        self._copies: dict[int, bytes] = {}  # no store, no frame_source: their lossless grey copy (``grey_copy``)
        self._late: OrderedDict[int, Features] = OrderedDict()  # features of ``_unextracted`` keyframes (LRU)
        self._late_size = rt["feature_cache"]
        self._geometries: OrderedDict[tuple[int, int], GeometryResult] = OrderedDict()  # ``verified_geometry``

    def _load(self, db: KeyframeDatabase) -> None:
        """Rebuilds the place memory and the filter's history from the database, as the uninterrupted run had them:
        each keyframe is registered again in frame order (searched again only for a filter whose state depends on
        every search: it is updated with what it saw then), then committed with its stored hypotheses and inserted;
        online, the stream's calibration goes on from the state stored at its last refit (``_load_online``)."""
        n = 0
        results, loops = {}, {}
        for q, cands, loop in db.results():
            results[q], loops[q] = cands, loop
        resume = _OnlineResume(self, db, results, loops) if self._online is not None else None
        if not self.filter.replays_history and resume is None:  # else every search is replayed as it was then
            restored = self.places.restore_index(db.index_path, db.keyframe_ids())
            if restored:
                log.info("restored the place index of %d keyframes from %s", restored, db.index_path)
        read_features = self.features.db is None and not self._keep_image  # database / image mode: read when needed
        for fid, entry, timestamp, feats in db.search_entries(features=read_features):
            entry = entry if resume is None else resume.entry(fid, entry)
            try:
                self.places.check(entry)  # the store keeps the searched entry itself
            except ConfigError as err:
                raise ConfigError(f"{db.path}: keyframe {fid}: {err}; the database is damaged") from None
            if self.filter.replays_history:  # its state depends on every update, not only on the kept hypotheses
                scores, ids = self.places.search(fid, entry, timestamp, self.conf["search"]["k"])
                self.filter.update(fid, ids[scores >= self.conf["search"]["min_score"]], self.places.source)
            else:
                self.places.register(fid, entry, timestamp)
            self.filter.commit(fid, results[fid][:, 0].astype(np.int64))
            if resume is not None:
                resume.decide(fid)  # the decision's state: as the stream's frame decided it
            elif self.decision is not None:  # stored rows: frame_id, score, matches, inliers, ... (CANDIDATE_ROW)
                self._replay(self.decision, self._confirm, fid, results[fid], loops[fid])
            self.places.insert(fid, entry, timestamp)
            # database mode (feats None): read back from the database when needed
            if db.has_image(fid) or (feats is not None and not len(feats) and self._frame_source is not None):
                self._unextracted.add(fid)  # not extracted then (or none found): again when needed
            elif feats is not None:  # memory mode: everything back in memory
                self.features[fid] = feats
            if resume is not None:
                resume.after(fid)
            n += 1
        self._next_id = db.last_frame_id() + 1
        if n:
            log.info("resumed %s: %d keyframes, next frame %d", db.path, n, self._next_id)

    @property
    def calibrates_online(self) -> bool:
        """Whether the stream calibrates itself (``retrieval.online``): its keyframe store then keeps each keyframe's
        raw code (``FrameResult.code``), not its searched entry, and a refit moves the searched entries."""
        return self._online is not None

    @property
    def deciding_calibration(self) -> Calibration | None:
        """The calibration that decides now: None in an online warm-up (or while a carried one is unchecked) and
        under the fixed policy; online, the stream's latest fit (replaced at each refit)."""
        return None if self._online is not None and not self._online.ready else self.calibration

    @property
    def next_frame_id(self) -> int:
        """The frame id ``process`` assigns when none is given (one past the last frame seen)."""
        return self._next_id

    def _frame_id(self, frame_id: int | None) -> int:
        """Checks a frame id given to ``process``; changes nothing."""
        if self._closed:
            raise ConfigError("this LoopDetector is closed; create a new one")
        if frame_id is None:
            return self._next_id
        frame_id = check_frame_id(frame_id, "frame_id")
        if frame_id < self._next_id:
            raise ConfigError(f"frame id {frame_id} is not after the last frame processed ({self._next_id - 1})")
        return int(frame_id)

    def record_unreadable(self, frame_id: int | None = None, source: str = "", fingerprint: str = "",
                          message: str = "") -> int:
        """Records that frame ``frame_id`` could not be read (it takes its id, so later ids stay stable).

        Returns:
            The frame id used.
        """
        fid = self._frame_id(frame_id)
        if self.db is not None:
            self.db.add_skipped(fid, "unreadable", source, fingerprint, message=message)
        self._next_id = fid + 1
        return fid

    def process(self, image: np.ndarray, frame_id: int | None = None, timestamp: float | None = None,
                pose: np.ndarray | None = None, source: str = "", fingerprint: str = "",
                code: np.ndarray | None = None) -> FrameResult:
        """Runs one frame through the pipeline and inserts it as a keyframe if it passes the gate.

        Args:
            image: grey/BGR/BGRA, uint8/uint16/float, at least 8x8 (as ``cv2.imread(..., IMREAD_UNCHANGED)`` gives).
            frame_id: increasing integer id; None = one past the previous frame.
            timestamp: seconds, finite (used by ``search.exclude_recent_s`` and stored).
            pose: ``(3, 4)`` (or ``(4, 4)``) camera-to-world pose, finite, stored with the keyframe when given.
            source: free text stored with the keyframe (e.g. the file name).
            fingerprint: ``"size:hash"`` of the source file (``cae_lcd.core.images.fingerprint``), stored to check resumes.
            code: this frame's raw ``(dim,)`` global code when it was already computed from the same image (``detect``
                encodes ahead, in batches, and reuses the calibration's codes); None: encoded here.

        Raises:
            ImageError: ``image`` is not an image array we can use (not an array, bad shape, too small, ...).
            ConfigError: a bad ``frame_id``, ``timestamp``, ``pose`` or ``code``, or the detector is closed.
                In every case the detector's state is left as it was.
        """
        fid = self._frame_id(frame_id)
        check_image(image, "image")
        ts = None if timestamp is None else check_timestamp(timestamp)
        pose34 = None if pose is None else check_pose(pose)
        if code is not None:
            code = self._given_code(code)
        ms: dict[str, float] = {}
        t_start = t0 = time.perf_counter()
        image8, gray, prep = self._prepared_frame(fid, image)
        if self._jobs is not None and fid not in self._given and self._features_wanted:
            # the worker starts now, first: its extraction is the longer of the two that run side by side
            self._jobs.submit(fid, functools.partial(_own_features, prep), urgent=True)
        net = self.descriptor.network_image(image8) if code is None else None  # the encoder's input
        gate = self.gate(gray)
        ms["gate"] = (time.perf_counter() - t0) * 1e3
        if not gate.passed:
            if self.db is not None:
                self.db.add_gated(fid, source, fingerprint, gate.edge_ratio)
            self._next_id = fid + 1
            ms["total"] = (time.perf_counter() - t_start) * 1e3
            return FrameResult(fid, True, gate.edge_ratio, ms=ms)

        feats, code, entry, candidates = self._describe_and_search(image, gray, prep, net, fid, ts, ms, code)
        try:
            loop, best, confirmed = self._verify_and_insert(fid, gate.edge_ratio, feats, code, entry, prep,
                                                            candidates, ts, pose34, source, fingerprint, ms)
        except BaseException:
            self.places.undo(fid)  # the frame is not in the map: the state is as it was
            raise
        ms["total"] = (time.perf_counter() - t_start) * 1e3
        geo = best.geometry if best is not None else None
        return FrameResult(fid, False, gate.edge_ratio, candidates, loop, getattr(geo, "R", None),
                           getattr(geo, "t", None), ms, entry, best, confirmed, code)

    def _verify_and_insert(self, fid: int, edge_ratio: float, feats: Features | None, code: np.ndarray,
                           entry: np.ndarray, prep: Callable[[], tuple[np.ndarray, float, bytes]],
                           candidates: list[Candidate], ts: float | None, pose34: np.ndarray | None, source: str,
                           fingerprint: str, ms: dict[str, float]
                           ) -> tuple[Candidate | None, Verification | None, list[tuple[int, Candidate]]]:
        """Verifies the hypotheses, decides (the loop, its check, the delayed loops it confirms: ``_confirmed``), and
        stores the keyframe (database first, then memory)."""
        t0, f0 = time.perf_counter(), ms["features"]
        refs = np.array([cd.frame_id for cd in candidates], np.int64)
        # what the decision reads from the codes alone: first, beside the worker extracting the query's features
        terms = self.decision.code_terms(fid, refs, self.places.source, windows=False) \
            if self.decision is not None else None
        feats, checks = self._check(fid, feats, prep, candidates, ms)
        self._keep_geometries(fid, candidates, checks)
        if feats is None:
            feats = self._given.pop(fid, None)  # extracted before (calibration): kept, as if extracted now
        for cand, check in zip(candidates, checks):
            if check is not None:
                cand.matches, cand.inliers = check.matches, check.inliers
            else:
                cand.inliers = -1
        for cand, own in zip(candidates, self._confidences(candidates)):
            cand.confidence = own
        if self.decision is not None:
            fused = self.decision.confidences(fid, refs, np.array([self._counted(cd) for cd in candidates], np.int64),
                                              self.places.source, np.array([cd.confidence for cd in candidates]),
                                              terms)
            for cand, value in zip(candidates, fused):
                cand.confidence = float(max(value, -1e9))
        loop, best = self._decide(fid, candidates, checks)
        if loop is not None and best is not None and feats is not None and self._localiser is not None:
            loop, best = self._localise(fid, feats, loop, best, candidates, checks)
        if self.decision is not None:
            self.decision.note_loop(fid, None if loop is None else loop.frame_id,
                                    0.0 if loop is None else loop.confidence)
        confirmed = self._confirmed(fid, candidates, loop)
        ms["verify"] = (time.perf_counter() - t0) * 1e3 - (ms["features"] - f0)  # late extraction not counted

        t0 = time.perf_counter()
        self._insert(fid, edge_ratio, feats, code, entry, prep, candidates, loop, ts, pose34, source, fingerprint)
        ms["insert"] = (time.perf_counter() - t0) * 1e3
        if self._online is not None:
            t0 = time.perf_counter()
            if not self._online.ready and self._online.next_fit <= self._late_size:
                self._queue_warm_up(fid, prep)  # the first fit verifies pairs across the whole warm-up: the worker
                #                                 extracts each keyframe's features ahead, beside the frames that follow
            self._online.record(fid, edge_ratio, code, np.array([cd.frame_id for cd in candidates], np.int64),
                                np.array([cd.matches for cd in candidates], np.int64),
                                np.array([cd.inliers for cd in candidates], np.int64),
                                loop is not None)
            confirmed = confirmed + self._online_step()
            self._reported(fid, confirmed)
            ms["calibrate"] = (time.perf_counter() - t0) * 1e3
        return loop, best, confirmed

    def _insert(self, fid: int, edge_ratio: float, feats: Features | None, code: np.ndarray, entry: np.ndarray,
                prep: Callable[[], tuple[np.ndarray, float, bytes]], candidates: list[Candidate],
                loop: Candidate | None, ts: float | None, pose34: np.ndarray | None, source: str,
                fingerprint: str) -> None:
        """Stores the decided keyframe: the database first (if the disk refuses it, the in-memory state has not
        moved either), then the place memory, the filter's and the decision's state, and its local features (kept,
        or how to extract them again)."""
        if self.db is not None:
            rows = np.array([cd.as_row() for cd in candidates], np.float64).reshape(-1, len(CANDIDATE_ROW))
            stored = feats if feats is not None and self._store_features else self._no_features()
            self.db.append(KeyframeRecord(fid, self.places.stored(entry) if self._online is None else code, stored,
                                          ts, pose34, source, edge_ratio, rows, -1 if loop is None else loop.frame_id,
                                          fingerprint, prep()[2] if self._keep_image and feats is None else b""))
        self.places.insert(fid, entry, ts)
        refs = np.array([cd.frame_id for cd in candidates], np.int64)
        self.filter.commit(fid, refs)
        if self.decision is not None:
            self.decision.commit(fid, refs, np.array([self._counted(cd) for cd in candidates], np.int64))
        if feats is not None:
            self.features[fid] = feats  # after the database has it: database mode may read it back from there
        else:  # not kept: extracted (again) if a query needs it (frame_source, the stored copy, or one kept here)
            self._unextracted.add(fid)
            if self._frame_source is None and not self._keep_image:
                small, scale, _ = prep()
                self._copies[fid] = grey_copy(small, scale)
        self._next_id = fid + 1

    def _describe_and_search(self, image: np.ndarray, gray: np.ndarray,
                             prep: Callable[[], tuple[np.ndarray, float, bytes]], net: np.ndarray | None, fid: int,
                             ts: float | None, ms: dict[str, float], code: np.ndarray | None = None
                             ) -> tuple[Features | None, np.ndarray, np.ndarray, list[Candidate]]:
        """Local features (None: lazy, not extracted yet), the raw code and the searched entry, and the top-k
        hypotheses of one frame (stage times into ``ms``). The search registered the frame in ``places.source``
        (``places.undo`` forgets it)."""
        # local features: first when the descriptor needs them, else (not lazy) after search, from the worker when it
        # started them (``process``); none when nothing verifies with them; lazy: when a candidate needs them
        feats = None
        ms["features"] = 0.0
        if self.descriptor.needs_features:
            t0 = time.perf_counter()
            feats = self.extractor.extract(gray)
            ms["features"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        if code is None:
            code = self.descriptor(image, feats, network_image=net)
        if self._online is not None:  # the raw code as kept (float16: a refit, and a resumed run, whiten it again)
            code = np.asarray(code, np.float16).astype(np.float32)
        entry = self.places.entry(code)
        ms["encode"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        k = self.conf["search"]["k"]
        scores, ids = self.places.search(fid, entry, ts, k)
        ids = ids[scores >= self.conf["search"]["min_score"]]
        ms["search"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        hyp, seq = self.filter.update(fid, ids, self.places.source)
        kept = np.arange(len(hyp)) < k  # the top k, and the keyframe a stop would carry the frame before's loop to
        if self.decision is not None:  # (a reference stop's frames all look alike: its rank among them is noise)
            kept |= np.isin(hyp, self.decision.carry_to(fid))
        hyp, seq = hyp[kept], seq[kept]
        single = self.places.source.pairs(np.full(len(hyp), fid), hyp)
        candidates = [Candidate(int(i), float(s), seq_score=float(q)) for i, s, q in zip(hyp, single, seq)]
        ms["filter"] = (time.perf_counter() - t0) * 1e3
        if feats is None and not self._lazy:
            t0 = time.perf_counter()
            if self._verify and fid in self._given:
                feats = self._given.pop(fid)
            else:
                feats = self._own(fid, prep) if self._verify or self._online is not None else self._no_features()
            ms["features"] = ms["features_wait"] = (time.perf_counter() - t0) * 1e3  # what the frame waited
        return feats, code, entry, candidates

    def prefetch_features(self, image: np.ndarray, frame_id: int) -> bool:
        """Starts extracting the local features of a frame still to come, on the feature worker, where the stream
        wants them (``runtime.lazy_features`` off, or the frame processed last verified a candidate): ``process``
        with this same ``image`` object and ``frame_id`` then takes them as its own. A caller holding the next frames
        (``cae-lcd detect`` reads ahead) calls it for them before ``process`` of the current one, so that their
        extraction runs while this one is verified. At most ``MAX_PREFETCHED`` frames are held (later calls are
        refused); ``process`` of a frame drops those of earlier ids, and a prefetch of the same id with another
        image (its job too). Nothing is decided or stored here.

        Returns:
            True when the frame's extraction is started (now or by an earlier call with the same image).

        Raises:
            ImageError: ``image`` is not an image array ``process`` takes.
            ConfigError: ``frame_id`` is not an id after the last frame processed, or the detector is closed.
        """
        fid = self._frame_id(frame_id)
        check_image(image, "image")
        held = self._ahead.get(fid)
        if held is not None and held[0] is image:
            return True
        self._drop_ahead(lambda f: f == fid)
        if self._jobs is None or fid in self._given or fid in self._jobs or not self._features_wanted \
                or len(self._ahead) >= MAX_PREFETCHED:
            return False
        image8, gray, prep = self._frame_images(image)
        self._ahead[fid] = (image, image8, gray, prep)
        self._jobs.submit(fid, functools.partial(_own_features, prep))
        return True

    @property
    def _features_wanted(self) -> bool:
        """Whether a frame's own local features are extracted as it comes (not lazy, or the frame before verified a
        candidate: a revisit under way), rather than only once a candidate needs them."""
        return not self._lazy or self._wanted

    def _prepared_frame(self, fid: int, image: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, Callable[[], tuple[np.ndarray, float, bytes]]]:
        """``(image as uint8, grey uint8, its features' prepared image once)`` of frame ``fid``: those of
        ``prefetch_features`` when it was called with this image and id, else made here; the prefetches of this
        frame with another image and of earlier frames dropped."""
        held = self._ahead.pop(fid, None)
        if held is not None and held[0] is not image:
            self._jobs.drop(fid)
            held = None
        self._drop_ahead(lambda f: f < fid)
        return (held[1], held[2], held[3]) if held is not None else self._frame_images(image)

    def _frame_images(self, image: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, Callable[[], tuple[np.ndarray, float, bytes]]]:
        """``(image as uint8, grey uint8, its features' prepared image once)`` of an accepted image."""
        image8 = to_uint8(image)  # once: 16-bit and float frames are scanned and scaled here only
        gray = to_gray_u8(image8)
        return image8, gray, self._prepare_once(gray)

    def _drop_ahead(self, which: Callable[[int], bool]) -> None:
        """Forgets the prefetched frames ``which`` says and their extraction jobs (their features would be other
        images')."""
        for fid in [f for f in self._ahead if which(f)]:
            del self._ahead[fid]
            if self._jobs is not None:
                self._jobs.drop(fid)

    def _prepare_once(self, gray: np.ndarray) -> Callable[[], tuple[np.ndarray, float, bytes]]:
        """``() -> (image, scale, copy)``, computed once (by whichever thread asks first): the grey image a frame's
        local features are extracted from and its scale (``FeatureExtractor.prepare``), and the grey copy a store
        keeps of it (``runtime.features: image``; the image is then the copy decoded, so that the frame's features
        are the ones its copy gives again later), else b""."""
        box: list[tuple[np.ndarray, float, bytes]] = []
        lock = threading.Lock()

        def get() -> tuple[np.ndarray, float, bytes]:
            with lock:
                if not box:
                    small, scale = self.extractor.prepare(gray)
                    copy = grey_copy(small, scale, self.conf["runtime"]["image_quality"]) if self._keep_image else b""
                    box.append((read_grey_copy(copy)[0] if copy else small, scale, copy))
                return box[0]
        return get

    def _own(self, fid: int, prep: Callable[[], tuple[np.ndarray, float, bytes]]) -> Features:
        """The frame's own local features: the worker's (waited for when it runs them), else extracted here."""
        feats = self._jobs.take(fid, self.extractor) if self._jobs is not None else None
        return feats if feats is not None else _own_features(prep, self.extractor)

    def _no_features(self) -> Features:
        return Features.empty(self.extractor.descriptor_dim, self.extractor.descriptor_dtype, self.extractor.metric)

    def _given_code(self, code: Any) -> np.ndarray:
        """Checks a code given to ``process``: ``(dim,)``, finite; changes nothing."""
        arr = np.asarray(code) if isinstance(code, np.ndarray) else None
        if arr is None or arr.shape != (self.descriptor.dim,) or not np.issubdtype(arr.dtype, np.floating) \
                or not np.isfinite(arr).all():
            raise ConfigError(f"code must be a finite float array of shape ({self.descriptor.dim},) (this "
                              f"descriptor's raw code); got {getattr(arr, 'shape', type(code).__name__)}")
        return arr.astype(np.float32, copy=False)

    def _could_pass(self, cand: Candidate) -> bool:
        """Whether verifying ``cand`` could make it a loop: verification is on and, calibrated, its temporal score or
        its single-frame score is above chance (``search.verify_min_z`` sigmas over the far-side null's median; the
        single frame's sigma taken as ``sqrt(length)`` times the temporal one, as for an average of ``length``
        independent terms: at the first frame of a revisit the temporal score holds one term only); uncalibrated,
        it reaches ``policy.min_seq_score``."""
        if not self._verify:
            return False
        cal, z, floor = self.calibration, self.conf["search"]["verify_min_z"], self.conf["policy"]["min_seq_score"]
        if cal is not None and cal.score_null and z is not None:
            median, sigma = cal.score_null["median"], cal.score_null["sigma"]
            length = float(self.conf["temporal"].get("length", 1))
            return cand.seq_score >= median + z * sigma or cand.score >= median + z * sigma * math.sqrt(length)
        return cal is not None or floor is None or cand.seq_score >= floor

    def _check(self, fid: int, feats: Features | None, prep: Callable[[], tuple[np.ndarray, float, bytes]],
               candidates: list[Candidate], ms: dict[str, float]) -> tuple[Features | None, list[Verification | None]]:
        """Verifies the candidates that could pass (``_could_pass``); the query's features extracted here when
        lazy and needed (time into ``ms["features"]``: the worker extracts the query's while this thread gets the
        candidates'), the candidates' from memory, or extracted again."""
        c = self.conf
        todo = [i for i, cd in enumerate(candidates) if self._could_pass(cd)]
        checks: list[Verification | None] = [None] * len(candidates)
        self._wanted = bool(todo)
        if not todo:
            return feats, checks
        t0 = time.perf_counter()
        if feats is None:
            feats = self._given.pop(fid, None)
        if feats is None and self._jobs is not None:
            self._jobs.submit(fid, functools.partial(_own_features, prep), urgent=True)  # unless started already
        self._queue_copies([candidates[i].frame_id for i in todo])  # the worker takes the next one, after the query
        refs = [self._features_of(candidates[i].frame_id) for i in todo]
        if feats is None:
            feats = self._own(fid, prep)
        ms["features"] += (time.perf_counter() - t0) * 1e3
        self._prefetch([candidates[i].frame_id for i in todo])
        done = self.verifier.verify(feats, refs, self.K, c["policy"]["min_matches"], self._min_inliers,
                                    c["policy"]["check_all"], self._pool)
        for i, check in zip(todo, done):
            checks[i] = check
        return feats, checks

    def _prefetch(self, verified: list[int]) -> None:
        """Queues in the worker the features of the keyframes just after ``verified`` ones (the next frames' likely
        candidates on a revisit)."""
        self._queue_copies(sorted({f + d for f in verified for d in (1, 2)}))

    def _queue_copies(self, fids: list[int]) -> None:
        """Queues in the worker, in this order, the features of the keyframes ``fids`` that are not kept and come
        from a grey copy (read here, in this thread); a job this thread takes first it runs itself (``take``)."""
        if self._jobs is None or self._frame_source is not None:
            return
        for nxt in fids:
            if self._awaits_extraction(nxt):
                copy = self._copy_of(nxt)
                if copy:
                    self._jobs.submit(nxt, functools.partial(_copy_features, copy))

    def _queue_warm_up(self, fid: int, prep: Callable[[], tuple[np.ndarray, float, bytes]]) -> None:
        """Queues in the worker the features of warm-up keyframe ``fid`` (not kept), from the frame in hand: its
        prepared image (``prep``), which its grey copy, where one is kept, gives back pixel for pixel (a lossless
        one, ``grey_copy``: not decoded again), and which a ``frame_source`` (``detect``) would read again."""
        if self._jobs is not None and self._awaits_extraction(fid):
            self._jobs.submit(fid, functools.partial(_own_features, prep))

    def _awaits_extraction(self, fid: int) -> bool:
        """Whether keyframe ``fid``'s features are nowhere to be had yet: not kept, not cached, not given, not queued
        (the worker, ``self._jobs``, must exist)."""
        return fid in self._unextracted and fid not in self._late and fid not in self._given and fid not in self._jobs

    def _copy_of(self, fid: int) -> bytes:
        """A keyframe's grey copy (``grey_copy``): kept here, or read from the store; b"" when there is none."""
        if fid in self._copies:
            return self._copies[fid]
        return self.db.image(fid) if self.db is not None and self.db.has_image(fid) else b""

    def keyframe_features(self, frame_id: int) -> Features:
        """A processed keyframe's local features: kept, or extracted now from its image again and cached (the run
        extracts them lazily: only for frames whose candidates could pass).

        Raises:
            KeyError: ``frame_id`` is no keyframe of this detector.
        """
        return self._features_of(int(frame_id))

    def _features_of(self, fid: int) -> Features:
        """A keyframe's local features: kept, or extracted now (its image again: the worker's job when queued) and
        cached (LRU)."""
        if fid not in self._unextracted:
            return self.features[fid]
        given = self._given.get(fid)
        if given is not None:
            return given.compact()
        feats = self._late.get(fid)
        if feats is not None:
            self._late.move_to_end(fid)
            return feats
        feats = self._jobs.take(fid, self.extractor) if self._jobs is not None else None
        if feats is None:
            feats = self._extract_late(fid)
        return self._cache_late(fid, feats)

    def _cache_late(self, fid: int, feats: Features) -> Features:
        """Keeps ``fid``'s features (compacted) among the late ones, the least recently used dropped; returns them."""
        feats = self._late[fid] = feats.compact()
        while len(self._late) > self._late_size:
            self._late.popitem(last=False)
        return feats

    def _extract_late(self, fid: int) -> Features:
        """Extracts here the features of a keyframe processed earlier without keeping them."""
        if self._frame_source is not None:
            return self.extractor.extract(to_gray_u8(to_uint8(self._frame_source(fid))))
        return _copy_features(self._copy_of(fid), self.extractor)

    def _reported(self, fid: int, confirmed: list[tuple[int, Candidate]]) -> None:
        """Records the delayed loops reported after keyframe ``fid`` (``_delayed``, the first one of a frame kept;
        marked in the online state), then, after a refit, the online state in the store (``_save_online``)."""
        self._online.mark([q for q, _ in confirmed])
        for q, cand in confirmed:
            self._delayed.setdefault(int(q), (cand.frame_id, cand.confidence))
        if self._refitted is not None and self.db is not None:
            self._save_online(fid)
        self._refitted = None

    def _save_online(self, fid: int) -> None:
        """Writes the online state after keyframe ``fid`` into the store (``KeyframeDatabase.write_online``): a
        resumed run starts from it (``_load_online``)."""
        meta, arrays = self._online.to_state()
        delayed = np.array([(q, r, c) for q, (r, c) in sorted(self._delayed.items())], np.float64).reshape(-1, 3)
        self.db.write_online(fid, {**meta, "rewhitened": self._refitted}, {**arrays, "delayed": delayed})

    def _online_step(self) -> list[tuple[int, Candidate]]:
        """The stream's own calibration (``retrieval.online``), after a keyframe is stored: at the end of the warm-up
        a carried calibration is checked, else fitted; at doublings refitted; between them checked against the
        newest frames and refitted where they drifted, or where the inlier path cannot verify them (too few keypoints:
        ``OnlineCalibration.unverifiable``). Returns the loops a new decision finds late."""
        on = self._online
        step = on.due()
        if step is None:
            return []
        unverifiable = on.unverifiable(self.keyframe_features) if step == "check" and not on.unchecked else None
        if unverifiable is not None:
            log.info("online calibration at %d keyframes: the newest frames cannot be verified (median %.0f keypoints "
                     "< calibration.min_features): refit on them now", len(on.seen), unverifiable)
        elif step == "check" or on.unchecked:
            carried, on.unchecked = on.unchecked, False
            # a prior is checked on the whole warm-up
            z = on.drift(self.places.source, self.filter, self.descriptor.still_cos, 0 if carried else None)
            if z <= DRIFT_Z:
                on.next_fit = on.next_fit if not carried else 2 * len(on.seen)
                if carried:
                    on.ready = True
                    self._verify = bool(on.calibration.inlier_null)
                    self._refitted = False  # a decision from here: kept in the store (``_reported``)
                    log.info("carried calibration checked against the stream at %d keyframes: its far-side scores "
                             "%.1f sigma from its null: kept", len(on.seen), z)
                    return self._redecide()
                return []
            log.info("%s at %d keyframes: the stream's far-side scores lie %.1f sigma above its null: refit on the "
                     "stream", "carried calibration" if carried else "online calibration", len(on.seen), z)
            if carried:
                on.calibration = None  # refused: only the stream's own may decide now
        cal = on.fit(self.descriptor, self.K, self.keyframe_features)
        if cal is None:
            return []
        self._use(cal)
        self._refitted = True
        return self._redecide() if on.ready else []

    def _use(self, cal: Calibration) -> None:
        """Makes ``cal`` (fitted on the stream) the run's: the gate's reference, the index moved into its whitening,
        the decision, what is verified."""
        self._install(cal, cal.whitening is not self.places.whitening)
        self._verify = self._online.adopt(cal, self.places.source, self.filter, self.descriptor.still_cos) \
            and bool(cal.inlier_null)

    def _install(self, cal: Calibration, rewhiten: bool) -> None:
        """``cal`` the run's calibration and the gate's reference; with ``rewhiten`` every keyframe moved into its
        whitening (from the raw codes the stream kept)."""
        self.calibration = cal
        if cal.edge_reference is not None:
            self.gate.reference = cal.edge_reference
        if rewhiten:
            self.places.rewhiten(cal.whitening, *self._online.raw())
            self.whitening = cal.whitening

    def _redecide(self) -> list[tuple[int, Candidate]]:
        """The newest ``calibration.max_frames`` recorded frames (every one in a shorter stream) decided again under
        the current calibration, in order (scores in the current code space; candidates not verified that could
        pass now verified first, ``_verify_late``); the decision's state is the replay's; older frames keep their
        decisions (a refit's request stays bounded however long the map: 0.8 ms a frame replayed). Returns the
        loops not reported yet (``(frame_id, candidate)``)."""
        cal, c = self.calibration, self.conf
        self.decision = dec = cal.decision(c["search"]["exclude_recent"], self.filter)
        self._min_inliers = int(dec.floor)
        self._confirm = confirm = Confirmations(dec.reach) if dec.confirms else None
        src, out = self._replay_source(), []
        seens = self._online.seen[-c["calibration"]["max_frames"]:]
        rows = list(zip(seens, self._recorded(seens, src)))
        self._verify_late(rows)
        # what the codes alone say, every recorded frame's together (a frame the replay carries a stop to: again)
        terms = dec.code_terms_many(np.array([s.frame_id for s in seens], np.int64), [s.refs for s in seens], src)
        for (seen, cands), frame_terms in zip(rows, terms):
            q, refs = seen.frame_id, seen.refs
            carried = self._carry_candidates(q, refs, src)
            if carried:
                cands, refs = cands + carried, np.r_[refs, [cd.frame_id for cd in carried]].astype(np.int64)
                frame_terms = dec.code_terms(q, refs, src)
            for cand, own in zip(cands, self._confidences(cands)):
                cand.confidence = own
            counted = np.array([self._counted(cd) for cd in cands], np.int64)
            fused = dec.confidences(q, refs, counted, src, np.array([cd.confidence for cd in cands]), frame_terms)
            for cand, value in zip(cands, fused):
                cand.confidence = float(max(value, -1e9))
            loop = self._decide(q, cands, [None] * len(cands))[0]  # the run's rule, stop carry included
            dec.note_loop(q, None if loop is None else loop.frame_id, 0.0 if loop is None else loop.confidence)
            found = [] if loop is None else [(q, loop)]
            if confirm is not None:
                found += [(f, dataclasses.replace(cd, confidence=loop.confidence)) for f, cd in
                          (confirm.confirm(dec, q, loop.frame_id, self._counted(loop), src) if loop is not None
                           else [])]
                confirm.add(q, {cd.frame_id: (cd.confidence, cd) for cd in cands}, loop is not None)
            dec.commit(q, refs, counted)
            out += [(f, cd) for f, cd in found if not self._online.reported(f)]
            self._online.mark([f for f, _ in found])
        return self._walked_late(sorted({f: cd for f, cd in out}.items()))

    def pair_scores(self, query_id: int, ref_id: int) -> tuple[float, float]:
        """``(score, seq_score)`` of keyframes ``query_id`` and ``ref_id`` in the current code space: their entries'
        similarity and the temporal filter's score (NaN where either is not a keyframe)."""
        return self._pair_scores(query_id, ref_id, self.places.source)

    def _pair_scores(self, query_id: int, ref_id: int, src: SimilaritySource) -> tuple[float, float]:
        """``pair_scores`` on the similarity source ``src``."""
        q, r = np.array([query_id], np.int64), np.array([ref_id], np.int64)
        return float(src.pairs(q, r)[0]), float(self.filter.score(q, r, src)[0])

    def _carry_candidates(self, query_id: int, refs: np.ndarray, src: SimilaritySource) -> list[Candidate]:
        """The keyframe the replayed decision's stop carry names (``Decision.carry_to``) where frame ``query_id``'s
        recorded hypotheses ``refs`` lack it (the frame was no loop's carry when it was processed: the loop it
        carries came later, at a refit), as a candidate scored now in the current code space; not verified (a carry
        claims nothing new; ``src``: the replay's similarity source). Nordland streamed: the winter station stop, its
        loops found at a refit, was carried to frame 723 only, 224 not among 724's hypotheses."""
        out = []
        for ref in np.setdiff1d(self.decision.carry_to(query_id), refs).tolist():
            score, seq_score = self._pair_scores(query_id, ref, src)
            if np.isfinite(score):
                out.append(Candidate(int(ref), score, 0, -1, seq_score))
        return out

    def _replay_source(self) -> SimilaritySource:
        """The keyframes' current codes copied into a table (``retrieval.temporal.CodeTable``, the same admission
        rule) where they take at most ``REPLAY_COPY_BYTES``, else the place memory's own source: a replay scores tens
        of thousands of pairs, each read from the index otherwise (Nordland streamed: 2.7 of its 4.4 s of replays),
        with the same float32 products, so the same scores; each pair computed once (``memo``: the windows of
        neighbouring frames share most of their pairs, Nordland's replays scored 12.1 million pairs, 1.9 million
        distinct)."""
        src = self.places.source
        if len(src) * src.dim * 4 > REPLAY_COPY_BYTES:
            return src
        table = CodeTable(src.dim, src.searchable, memo=True)
        for fid, code in zip(*src.items()):
            table.add(int(fid), code)
        return table

    def _recorded(self, seens: list[Seen], src: SimilaritySource) -> list[list[Candidate]]:
        """Recorded frames' candidates (``retrieval.online.Seen``) with their scores in the current code space
        (``src``: ``_replay_source``), every frame's pairs scored together (``PAIR_CHUNK`` a call: the same scores as
        one frame at a time)."""
        queries = np.repeat(np.array([s.frame_id for s in seens], np.int64), [len(s.refs) for s in seens])
        refs = np.concatenate([s.refs for s in seens]).astype(np.int64) if seens else np.zeros(0, np.int64)
        sims, scores = np.zeros(len(refs)), np.zeros(len(refs))
        for lo in range(0, len(refs), PAIR_CHUNK):
            part = slice(lo, lo + PAIR_CHUNK)
            sims[part] = src.pairs(queries[part], refs[part])
            scores[part] = self.filter.score(queries[part], refs[part], src)
        out, lo = [], 0
        for seen in seens:
            hi = lo + len(seen.refs)
            out.append([Candidate(int(r), float(a), int(m), int(i), float(b)) for r, a, b, m, i in zip(
                seen.refs.tolist(), sims[lo:hi].tolist(), scores[lo:hi].tolist(), seen.matches.tolist(),
                seen.inliers.tolist())])
            lo = hi
        return out

    def _verify_late(self, rows: list[tuple[Seen, list[Candidate]]]) -> None:
        """Verifies, at a refit, the recorded frames' candidates that were not verified and could pass now
        (``_could_pass``; ``rows``: each frame's ``Seen`` and candidates), of the frames not yet a loop (a loop is
        reported once: more evidence there finds nothing new), every pair on its own (matching and the
        geometric check are per candidate with ``check_all``: the counts of one call per frame), side by side on
        the verify worker's thread and this one, ``LATE_BATCH`` pairs at a time (their features fetched here
        first); records their matches and inliers in both."""
        todo = [(seen, i, cd) for seen, cands in rows if not seen.reported for i, cd in enumerate(cands)
                if cd.inliers < 0 and self._could_pass(cd)]
        min_matches, verifiers = self.conf["policy"]["min_matches"], threading.local()

        def check(item: tuple[Seen, int, Candidate], feats: dict[int, Features]) -> Verification:
            if not hasattr(verifiers, "verifier"):  # one per thread (OpenCV and torch release the GIL)
                verifiers.verifier = create_verifier(self.conf["matcher"], self.conf["geometry"])
            seen, _, cd = item
            return verifiers.verifier.verify(feats[seen.frame_id], [feats[cd.frame_id]], self.K, min_matches,
                                             self._min_inliers, True)[0]

        for start in range(0, len(todo), LATE_BATCH):
            batch = todo[start:start + LATE_BATCH]
            feats = {f: self._features_of(f) for seen, _, cd in batch for f in (seen.frame_id, cd.frame_id)}
            done = side_by_side(functools.partial(check, feats=feats), batch, self._pool)
            for (seen, i, cd), got in zip(batch, done):
                cd.matches, cd.inliers = got.matches, got.inliers
                seen.matches[i], seen.inliers[i] = got.matches, got.inliers
                self._keep_geometries(seen.frame_id, [cd], [got])

    def _keep_geometries(self, fid: int, candidates: list[Candidate], checks: list[Verification | None]) -> None:
        """Keeps the checks of ``fid``'s candidates that found a pose (``verified_geometry``), ``kept_geometries`` at
        most."""
        if not self._kept_geometries:
            return
        for cd, check in zip(candidates, checks):
            if check is not None and check.geometry.essential is not None:
                self._geometries[(fid, cd.frame_id)] = check.geometry
                self._geometries.move_to_end((fid, cd.frame_id))
        while len(self._geometries) > self._kept_geometries:
            self._geometries.popitem(last=False)

    def verified_geometry(self, query: int, match: int) -> GeometryResult | None:
        """The two-view geometry this detector's check found for keyframe ``query`` against ``match``, where it found
        a pose (an essential matrix: intrinsics known) among the newest ``kept_geometries`` such checks; else None
        (not verified, no pose, none kept, dropped, or verified by an earlier process of a resumed run)."""
        return self._geometries.get((int(query), int(match)))

    def _confirmed(self, fid: int, candidates: list[Candidate],
                   loop: Candidate | None) -> list[tuple[int, Candidate]]:
        """The delayed loops the run accepting ``loop`` certifies (``retrieval.decision.Confirmations``), each a copy of
        the earlier frame's candidate with the run's confidence; records this frame. Before ``decision.commit``."""
        if self._confirm is None:
            return []
        out = [] if loop is None else [(q, dataclasses.replace(c, confidence=loop.confidence)) for q, c in
                                       self._confirm.confirm(self.decision, fid, loop.frame_id, self._counted(loop),
                                                             self.places.source)]
        self._confirm.add(fid, {cd.frame_id: (cd.confidence, cd) for cd in candidates}, loop is not None)
        return self._walked_late(out)

    def confirmed_loops(self, rows: Iterable[tuple[int, np.ndarray, int]]) -> dict[int, tuple[int, float]]:
        """``{frame_id: (keyframe, confidence)}``: the delayed loops (``FrameResult.confirmed``, with the accepting
        run's confidence) of a whole run, replayed from its stored rows (``KeyframeDatabase.results``: ``(frame_id,
        candidates (k, 6), loop)``), as the stream reported them; a resumed run's too. Empty without a calibrated,
        fused decision (``Decision.confirms``)."""
        if self._online is not None:  # as the stream reported them (refits included), kept in the store
            return dict(self._delayed)
        if self._confirm is None:
            return {}
        decision, confirm = self.decision.fresh(), Confirmations(self.decision.reach)
        out: dict[int, tuple[int, float]] = {}
        for fid, cands, loop in rows:
            out.update(self._replay(decision, confirm, fid, cands, loop))
        return {q: (cd.frame_id, cd.confidence) for q, cd in
                self._walked_late([(q, Candidate(r, 0.0, confidence=c)) for q, (r, c) in sorted(out.items())])}

    def _replay(self, decision: Decision, confirm: Confirmations | None, fid: int, rows: np.ndarray,
                loop: int) -> dict[int, tuple[int, float]]:
        """Replays one stored frame (``rows`` ``(k, 6)`` in ``CANDIDATE_ROW`` order, ``loop`` -1 or its keyframe)
        into ``decision`` and ``confirm``; returns the delayed loops ``{frame_id: (keyframe, confidence)}`` it
        confirms."""
        refs = rows[:, 0].astype(np.int64)
        counted = np.where(rows[:, 2] >= self.conf["policy"]["min_matches"], rows[:, 3], -1).astype(np.int64)
        out = {}
        if confirm is not None:
            hit = np.flatnonzero(refs == loop)
            if loop >= 0 and len(hit):
                out = {q: (r, float(rows[hit[0], 5])) for q, r in
                       confirm.confirm(decision, fid, int(loop), int(counted[hit[0]]), self.places.source)}
            confirm.add(fid, {int(r): (float(c), int(r)) for r, c in zip(refs.tolist(), rows[:, 5].tolist())},
                        loop >= 0)
        decision.commit(fid, refs, counted)
        return out

    def _counted(self, cand: Candidate) -> int:
        """The inliers that count as evidence (-1 where the check did not run or the matches are too few)."""
        return cand.inliers if cand.matches >= self.conf["policy"]["min_matches"] else -1

    def _confidences(self, cands: list[Candidate]) -> list[float]:
        """Each candidate's own confidence: calibrated, ``-log10 NFA`` on the deciding path (``Calibration.path``;
        -1e9 at least), every candidate's in one call; else the inlier count (the temporal score when the policy does
        not verify)."""
        cal = self.calibration
        if cal is None:
            return [float(cd.inliers) if self._verify else cd.seq_score for cd in cands]
        inliers = np.array([self._counted(cd) for cd in cands], np.int64)
        return np.maximum(cal.confidences(np.array([cd.seq_score for cd in cands], np.float64), inliers),
                          -1e9).tolist()

    def _passes_policy(self, cand: Candidate) -> bool:
        """The uncalibrated acceptance rule (``policy``)."""
        p = self.conf["policy"]
        if self._verify and (cand.matches < p["min_matches"] or cand.inliers < p["min_inliers"]):
            return False
        return p["min_seq_score"] is None or cand.seq_score >= p["min_seq_score"]

    def _decide(self, fid: int, candidates: list[Candidate],
                checks: list[Verification | None]) -> tuple[Candidate | None, Verification | None]:
        """The accepted candidate of frame ``fid``.

        Calibrated: the most confident one whose confidence reaches ``Calibration.accept_at`` (among equals one frame
        apart, the one whose own pair is most alike: ``_placed``). Uncalibrated: one that
        passes every policy threshold and is older than the stop a still camera has not left
        (``policy.still_cos``); most inliers, then most matches, then score (verifying), else the best temporal
        score (as ``evaluation``'s sweep on ``confidence`` picks it).
        """
        if self._online is not None and not self._online.ready:
            return None, None  # the warm-up, or a carried calibration not yet checked: nothing is accepted
        if self.calibration is not None:
            passing = [(cd, ch) for cd, ch in zip(candidates, checks) if cd.confidence >= self.calibration.accept_at]
            if not passing and self.decision is not None:  # a still frame after a loop: the same place (a stop)
                passing = self._carried(fid, candidates, checks)
            if not passing:
                return None, None
            return _placed(max(passing, key=lambda pair: (pair[0].confidence, pair[0].inliers, pair[0].seq_score)),
                           passing)
        passing = [(cd, ch) for cd, ch in zip(candidates, checks) if self._passes_policy(cd)]
        if passing and self._still is not None:  # only where a loop could be accepted: no cost elsewhere
            stop = int(self._still.lengths(np.array([fid], np.int64), self.places.source)[0])
            newest = fid - stop - self.conf["search"]["exclude_recent"]  # the stop counts as one frame
            passing = [(cd, ch) for cd, ch in passing if cd.frame_id <= newest]
        if not passing:
            return None, None
        key = (lambda pair: (pair[0].inliers, pair[0].matches, pair[0].score)) if self._verify else \
            (lambda pair: (pair[0].seq_score, pair[0].inliers, pair[0].score))
        return max(passing, key=key)

    def _localise(self, fid: int, feats: Features, loop: Candidate, check: Verification,
                  candidates: list[Candidate], checks: list[Verification | None]
                  ) -> tuple[Candidate | None, Verification | None]:
        """The accepted ``loop`` walked to the keyframe the query is at (``retrieval.localise``): the named one gets
        the loop's confidence; the others the walk verified are added to ``candidates`` and ``checks`` (their
        evidence counts for the frames after, as any verified candidate's; no hypothesis of their own: confidence
        -1e9). Where the walk names none (the query's place is not among the keyframes it may match) there is no
        loop, and every candidate that passed is vetoed (-1e9, as a too recent one: a replay of the stored rows
        decides the same). Returns the loop and its check (``loop``, ``check`` where the query is at it), or
        ``(None, None)``."""
        known = {cd.frame_id: ch for cd, ch in zip(candidates, checks) if ch is not None}
        src = self.places.source
        ref, walked = self._walk(fid, feats, loop.frame_id, check, known)
        if ref == loop.frame_id:
            return loop, check
        by_id = {cd.frame_id: i for i, cd in enumerate(candidates)}
        for r, got in walked:
            if r not in by_id:
                score, seq_score = self._pair_scores(fid, r, src)
                by_id[r] = len(candidates)
                candidates.append(Candidate(r, score, got.matches, got.inliers, seq_score, -1e9))
                checks.append(got)
        if ref is None:
            passed = (lambda cd: cd.confidence >= self.calibration.accept_at) if self.calibration is not None \
                else self._passes_policy
            for cd in [cd for cd in candidates if passed(cd)]:
                cd.confidence = -1e9
            log.debug("frame %d: loop to keyframe %d refused: its place lies beyond the keyframes it may match "
                      "(walked %s)", fid, loop.frame_id, [r for r, _ in walked])
            return None, None
        named, got = candidates[by_id[ref]], dict(walked)[ref]
        named.matches, named.inliers = got.matches, got.inliers
        named.confidence = max(named.confidence, loop.confidence)
        self._keep_geometries(fid, [named], [got])
        log.debug("frame %d: loop to keyframe %d walked to %d (%d -> %d inliers)", fid, loop.frame_id, ref,
                  loop.inliers, named.inliers)
        return named, got

    def _walked_late(self, found: list[tuple[int, Candidate]]) -> list[tuple[int, Candidate]]:
        """Delayed loops ``(frame, candidate)`` (a run's members, a refit's) walked as a frame's own loop is
        (``_localise``), each pair verified again from the keyframes' features: a copy with the keyframe named, or
        left out where none is. As is where the decision does not verify (the score path)."""
        if self._localiser is None or self.decision is None or self.decision.pair_tail is None or not found:
            return found
        out = []
        for q, cd in found:
            feats = self._features_of(q)
            ref, walked = self._walk(q, feats, cd.frame_id, self._verify_pair(feats, self._features_of(cd.frame_id)))
            if ref is None:
                log.debug("frame %d: delayed loop to keyframe %d refused: its place lies beyond the keyframes it may "
                          "match", q, cd.frame_id)
            elif ref == cd.frame_id:
                out.append((q, cd))
            else:
                got = dict(walked)[ref]
                score, seq_score = self._pair_scores(q, ref, self.places.source)
                out.append((q, dataclasses.replace(cd, frame_id=ref, score=score, seq_score=seq_score,
                                                   matches=got.matches, inliers=got.inliers)))
        return out

    def _walk(self, query_id: int, feats: Features, ref: int, check: Verification,
              known: dict[int, Verification] | None = None) -> tuple[int | None, list[tuple[int, Verification]]]:
        """``Localiser.walk`` of frame ``query_id`` (its features ``feats``) from keyframe ``ref`` (their ``check``)
        over this map: the keyframes before the query, those it may match older than its horizon
        (``Decision.horizon``; else the frame itself) and searchable."""
        src = self.places.source
        oldest = self.decision.horizon(query_id, src) \
            if self.decision is not None and self.decision.horizon is not None else query_id
        return self._localiser.walk(feats, ref, check, functools.partial(self._adjacent, before=query_id),
                                    lambda r: r < oldest and bool(src.searchable(np.array([r], np.int64))[0]), known)

    def _adjacent(self, ref: int, step: int, before: int) -> int | None:
        """The keyframe next to ``ref`` in the direction ``step`` (+1, -1) with an id below ``before``, gated frames
        skipped (``ADJACENT_SCAN`` ids at most); None where there is none."""
        for k in range(1, ADJACENT_SCAN + 1):
            r = ref + k * step
            if r < 0 or r >= before:
                return None
            if r in self.places.source:
                return r
        return None

    def _verify_pair(self, query: Features, ref: Features) -> Verification:
        """One pair's check as the run's candidates get it (``policy.min_matches``, the inlier floor)."""
        return self.verifier.verify(query, [ref], self.K, self.conf["policy"]["min_matches"], self._min_inliers,
                                    True)[0]

    def _carried(self, fid: int, candidates: list[Candidate],
                 checks: list[Verification | None]) -> list[tuple[Candidate, Verification | None]]:
        """The candidates in the reference's stop that the frame before's loop carries into this still frame
        (``Decision.stop_carry``), given the carried confidence."""
        inside, confidence = self.decision.stop_carry(fid, np.array([cd.frame_id for cd in candidates], np.int64),
                                                      self.places.source)
        for cd in (cd for cd, ok in zip(candidates, inside) if ok):
            cd.confidence = max(cd.confidence, confidence)
        return [(cd, ch) for cd, ch, ok in zip(candidates, checks, inside) if ok]

    def close(self) -> None:
        """Flushes and closes the database and stops the worker thread; ``process`` refuses to run afterwards."""
        self._closed = True
        self._ahead.clear()
        if self._jobs is not None:
            self._jobs.close()
            self._jobs = None
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None
        if self.db is not None:
            if self._online is None:  # online, a resume rebuilds the index in the stream's whitening
                self._save_index(self.db)
            self.db.close()

    def _save_index(self, db: KeyframeDatabase) -> None:
        """Saves the place index beside the store for the next resume (where rebuilding it would cost); a failure
        only costs that resume a rebuild."""
        try:
            if self.places.save_index(db.index_path):
                log.info("saved the place index of %d keyframes to %s", len(self.places), db.index_path)
        except OSError as err:
            log.warning("could not save the place index to %s (%s); a resume rebuilds it", db.index_path, err)

    def __enter__(self) -> "LoopDetector":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class _OnlineResume:
    """A resumed online run (``LoopDetector._load``, keyframe by keyframe in frame order): the keyframes up to the
    newest online state in the store (``last``, written at a refit: ``LoopDetector._save_online``) come back with it,
    searched as the stream searched them at that refit (from their raw codes, moved into its whitening there), the
    decision rebuilt as the refit rebuilt it; each keyframe after it is recorded and run through the schedule as the
    stream ran it (``_online_step``: checks, and a refit the store does not hold yet). The same loops as an
    uninterrupted run."""

    def __init__(self, det: LoopDetector, db: KeyframeDatabase, results: dict[int, np.ndarray],
                 loops: dict[int, int]) -> None:
        self.det, self.results, self.loops = det, results, loops
        ids = db.keyframe_ids()
        self.ratios = dict(zip(ids.tolist(), db.edge_ratios().tolist()))
        self.raw: dict[int, np.ndarray] = {}
        state = db.online_state(int(ids[-1])) if len(ids) else None
        self.last, self.meta, self.arrays = state if state is not None else (-1, {}, {})
        self.confirmed: dict[int, tuple[int, float]] = {}

    def entry(self, fid: int, raw: np.ndarray) -> np.ndarray:
        """The entry keyframe ``fid`` is registered with, from its stored raw code: in the current space, as the
        stream searched it (up to the stored state: moved with the others into its whitening there, ``_restore``)."""
        if raw.shape != (self.det.descriptor.dim,):
            raise ConfigError(f"keyframe {fid}: a stored raw code has shape {raw.shape} (expected "
                              f"({self.det.descriptor.dim},)); the database is damaged")
        self.raw[fid] = raw
        return self.det.places.entry(raw)

    def decide(self, fid: int) -> None:
        """The decision's state after keyframe ``fid``, as the stream's frame left it (its loop noted, its candidates
        committed); the delayed loops it confirmed kept for ``after``."""
        det, rows, loop = self.det, self.results[fid], self.loops[fid]
        self.confirmed = {}
        if det.decision is None:
            return
        hit = np.flatnonzero(rows[:, 0] == loop)
        det.decision.note_loop(fid, None if loop < 0 else loop, float(rows[hit[0], 5]) if loop >= 0 and len(hit)
                               else 0.0)
        self.confirmed = det._replay(det.decision, det._confirm, fid, rows, loop)

    def after(self, fid: int) -> None:
        """Keyframe ``fid`` inserted: at the stored state, the state taken back; after it, recorded and scheduled."""
        det = self.det
        if fid < self.last:
            return
        if fid == self.last:
            self._restore()
            return
        rows = self.results[fid]
        det._online.record(fid, self.ratios[fid], self.raw.pop(fid), rows[:, 0], rows[:, 2], rows[:, 3],
                           self.loops[fid] >= 0)
        found = det._walked_late([(q, Candidate(r, 0.0, confidence=c)) for q, (r, c) in self.confirmed.items()])
        det._reported(fid, found + det._online_step())

    def _restore(self) -> None:
        """The stored state taken back at its keyframe: the calibration, the codes moved into its whitening where
        its refit moved them, the decision rebuilt as the refit rebuilt it, the delayed loops reported."""
        det, on, meta = self.det, self.det._online, self.meta
        on.from_state(meta, self.arrays, self.raw, self.ratios)
        self.raw = {}
        det._delayed = {int(q): (int(r), float(c)) for q, r, c in np.asarray(self.arrays["delayed"]).tolist()}
        cal = on.calibration
        if cal is None:
            return
        det._install(cal, bool(meta["rewhitened"]))
        det._verify = on.ready and bool(cal.inlier_null)
        if on.ready:
            det._redecide()
        log.info("online calibration taken back from the store at keyframe %d (%s path)", self.last, cal.path)


def _own_features(prep: Callable[[], tuple[np.ndarray, float, bytes]], extractor: FeatureExtractor) -> Features:
    """A frame's local features from its prepared image (``LoopDetector._prepare_once``), with ``extractor``."""
    small, scale, _ = prep()
    return extractor.extract_prepared(small, scale)


def _copy_features(copy: bytes, extractor: FeatureExtractor) -> Features:
    """A keyframe's local features from its grey copy (``grey_copy``), with ``extractor``."""
    return extractor.extract_prepared(*read_grey_copy(copy))
