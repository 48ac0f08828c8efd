"""Thresholds that adapt to the camera: an a-contrario calibration from pairs known not to be loops.

Before a run, the calibration looks at the sequence itself (``cae-lcd calibrate PATH``, or the first step of
``cae-lcd detect``) and chooses, with the reasons printed:

1. **The gate's reference**: the median edge ratio of the sequence (``verify.gate``, relative mode).
2. **The code normalisation**: PCA-whitening fitted on the sequence's own codes (``cae.whitening``), each place
   weighed once: with ``whitening.skip_still`` (the default) a stop, the frames where the camera stood still (raw
   code unchanged from the frame before, cosine >= the weights' ``GlobalDescriptor.still_cos``), counts as its first
   frame only, not as often as the robot waited there (on Nordland 176 of 985 frames are three stations; fitted on them all, the whitening spends
   its variance on those few places and the waiting frames find no match); with ``whitening.source: weights``, the
   one ``cae-lcd train`` fitted on the training images and saved with the weights.
3. **The null distributions**: frames on the far side of the exclusion window (from half of ``search.exclude_recent``
   frames back to just inside it) are close in time, so they share the camera, the light and the season, but the
   camera has moved on, so they are not loops (a pair between which the camera stood still, its code unchanged frame
   after frame, is one place and is left out, and so is a pair whose *line* passes such a place: the pair moved back
   together over the frames its fused score reads, query and reference must have moved apart at every step, else
   the line's terms include one stop matched to itself and the nulls' tails hold a place, not a non-loop).
   **The score path's null is measured, not extrapolated** (issue 27): every far-side pair whose line stays half
   the window apart in frames where the camera *moved* (a stop in between does not make two frames of one station
   far apart), thousands of them (Nordland: about 11,000; a stream calibrating itself draws them out of sample:
   ``held_out``, from its newest frames under a whitening fitted on the frames before them, ``_out_of_sample``).
   Look-alike stretches recur at every distance (a railway's forest, a corridor's doors), where the far side does not
   reach, and a forward line there may be a revisit; so **reversed lines** between frames far apart join the sample
   (``_reversed_lines``, up to ``REVERSED_LINES``): the query's frames going back against the reference's going
   forward, which a revisit in the direction of travel crosses at one frame at most (a place longer than a window,
   a slow stretch into a station, can still lie on one: it raises the bar, it never lowers it; Nordland with a code
   that makes far stretches alike: summer frames closing on summer 181 back with the far side alone, none with the
   reversed lines). One window's temporal score is read from that sample as
   it is (``retrieval.decision.EmpiricalTail``: ``(#{null >= s} + 1) / (n + 1)``), so it claims at most
   ``log10(n + 1)`` decades, never a tail past the sample; the run tests about ``n_keyframes^2 / 2`` pairs at each
   of ``SPAN`` spans (Nordland: 2e6), which no one window can certify, so **a loop is a run of consecutive windows on
   one line** (``retrieval.decision.ScoreSpans``): each window must agree (its own p-value at most 0.1, ``AGREE``),
   their evidence is summed and read from the heavier of the Gamma tail (windows of disjoint frames taken as
   independent: the one assumption past the sample) and the fused evidence measured on the far-side lines of as many
   windows (``samples/score_fused``; where look-alike stretches make windows dependent, this raises the bar). The
   rule a reader can check: ``confidence = -log10(tests * max(Gamma_m(E), measured_m(E)))``, each window's term at
   most ``log10(n + 1)``; the notes say how many windows above every far-side pair a loop needs (Nordland, KITTI at
   64x32: 3 windows, 30 frames). Two vetoes keep the line's claim about *which* frame: the query's own window must
   not be beaten by more than ``LOCALISE`` decades on a line a few frames off (``ScoreSpans.localised``: the earlier
   windows of a line 3 frames off still read the true revisit), and the stop rule (``Stops``) holds on the query's
   frame and the one before. An accepted run certifies its earlier frames on the line (delayed loops,
   ``retrieval.decision.Confirmations``). ``score_null``'s median and 90th percentile only describe the null (the
   detector's "above chance" gate for verification). For the inlier path the null is what the detector really tests:
   the **hard negatives**, the two far-side keyframes retrieval would return for a sampled query (keeping
   ``exclude_recent // 10`` frames off the boundary), verified as in the run (a count under the floor,
   ``calibration.min_inliers``, is the geometric pre-check's, as for the run's candidates: no evidence either way;
   each distinct pair verified once), each followed back ``SPAN - 1``
   frames (look-alike streets look alike for several frames). A random far-side pair per query is verified too (and
   joins the null), to show the difference; the **positives** are a frame and its neighbour ``exclude_recent // 25``
   frames back, followed back likewise, for one sampled query in ``POSITIVE_EVERY`` (they only describe).
   ``retrieval.decision`` turns them into the pair null (issue 27: the measured sample itself, every pair of the hard
   sequences and the random ones, ``calibration.null_pairs`` verified pairs in all: an empirical p-value that
   claims nothing past the sample, ``retrieval.decision.EmpiricalTail``; one pair then never decides alone, a loop
   is a run of frames on one line, fused over up to ``SPAN`` frames) and the fused-evidence tail measured
   on the hard-negative sequences.
4. **Which path decides**: where local features can verify (the median frame has at least ``min_features``
   keypoints), geometry decides, fused over consecutive frames: the *inlier path*. Where they are too few (a 64x32
   camera), verification is switched off and the summary says so: loops then rest on the normalised code plus
   temporal consistency, the *score path*. A stream (``retrieval.online``) asks it of the frames it decides next,
   its newest ones (``newest_keypoints``): a revisit at night after a day's map has a day's keypoints in most of
   the frames a fit reads and too few to verify in the frames the stream is deciding. On a stream's inlier path the
   score path decides beside it (``SCORE_BESIDE_INLIERS``, its nulls drawn out of sample as where it decides alone):
   keypoints enough in number need not verify (a night frame's keypoints of noise), and each path keeps its own
   promise (``expected_false_loops / 2`` each, item 5).
5. **The threshold**, a-contrario: a candidate is accepted when the expected number of false loops at its strength
   over the whole run, ``NFA = tests * P_null(>= value)``, is at most ``expected_false_loops / 2`` on its path (two
   paths deciding side by side: at most ``expected_false_loops`` in all; the score path
   tests every query against every keyframe, at every span of fused windows; the inlier path tests ``k``
   candidates per query). The
   ``confidence`` of a candidate is ``-log10 NFA`` (the larger the surer); it is what ``loops.csv`` ranks by.
6. **Too recent**: the cosine under which a frame no longer looks like the query (the adjacent frames' 10th
   percentile); the run refuses keyframes of the stretch the query is still in (``retrieval.decision.Horizon``).
7. **Stops**: the normalised codes' cosine at which the camera stood still (the one that best reproduces, on the
   adjacent frames, the raw codes' verdict; ``STILL_COS`` where it never stood still); the run matches a still
   query only to a keyframe where the reference stood still at least as long (``retrieval.decision.Stops``).

``calibration.h5`` keeps every measured distribution under ``samples/`` (random, hard and positive inliers, hard and
positive fused evidence, adjacent cosines; the score path's window scores and fused evidence); the notes (printed,
and in ``summary.json``) summarise them.

**Its cost, and what is not its cost.** A fresh calibration reads and encodes every frame and extracts the local
features of the frames it verifies: that is the run's work done ahead (``detect`` hands the codes and features to the
run, which then does not redo it). Its own work is the edge ratios, the whitening, the nulls, verifying the sampled
pairs (side by side on every core: OpenCV and torch release the GIL) and the fits. Both are timed apart
(``Calibration.seconds``; ``summary.json`` ``seconds``: ``calibration`` in all, ``calibration_own``,
``calibration_shared``, ``frames``; one log line). Where local features are too few, a quarter of the planned pairs'
frames is looked at first and nothing is verified.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

import h5py
import numpy as np
from cae_lcd.core.progress import progress_bar as tqdm  # a bar on a terminal, log lines in a log

from cae.weights import STILL_COS  # for weights that do not say (``GlobalDescriptor.still_cos``)
from cae.whitening import MIN_FIT_CODES, Whitening
from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import DatabaseError
from cae_lcd.core.files import atomic_write
from cae_lcd.core.threads import cpu_count
from verify.features import create_extractor
from verify.gate import EdgeGate
from verify.verifier import create_verifier

from .decision import (AGREE, SPAN, TOL, Decision, EmpiricalTail, Horizon, MeasuredTail, ScoreSpans, Stops,
                       TailModel, fused_log10_sf, gaussian_log10_sf)
from .descriptors import GlobalDescriptor
from .temporal import PAIR_CHUNK, CodeTable, NoFilter, SequenceFilter, TemporalFilter

__all__ = ["Calibration", "TooFewFrames", "CALIBRATION_FORMAT", "calibrate", "calibrated_features",
           "run_needed", "windows_needed", "calibration_frames", "far_side_scores", "camera_moved", "score_level"]

log = logging.getLogger(__name__)

CALIBRATION_FORMAT = 4  #: ``format_version`` of calibration.h5 (3: the local features it was made on recorded; 4: the
#                           score path's nulls measured, ``samples/score_null`` and ``samples/score_fused``)
#: positives are verified for one sampled query in this many: they only describe (the notes, ``samples/``), no
#: decision reads them, and each costs the full check (3.4 ms against 1.2 for a hard negative the pre-check stops:
#: KITTI 90, every query's positives were 0.6 of the calibration's 2.0 CPU seconds)
POSITIVE_EVERY = 8
MIN_NULL_PAIRS = 20  #: far-side pairs a null (or a level read from them) needs at least
SCORE_BESIDE_INLIERS = True  #: a stream's fit on the inlier path lets the score path's fused windows decide beside it
#   (``Decision``'s ``both``: each path on its own budget), its nulls measured out of sample as where it decides alone:
#   a revisit whose frames keep keypoints but do not verify (night noise) is still found from its code and sequence
REVERSED_LINES = 20_000  #: the score path's long-range lines (``_reversed_lines``) drawn at most, seeded: a random
#   sample of every pair far enough apart where there are more (a stream of 2000 frames holds ~1.5 million). Nordland
#   streamed: 0 (before) recall 0.900, 13.4 ms a frame; 20,000: 0.922, 15.1 ms; 100,000: 0.930, 19.6 ms
_LN10 = math.log(10.0)


@dataclass
class Calibration:
    """What the calibration chose for one camera and sequence (see the module doc).

    Attributes:
        edge_reference: the sequence's median edge ratio (the relative gate's reference); None = not measured.
        whitening: the code normalisation, or None (raw cosine).
        score_null: ``{"median", "sigma", "samples", "empirical"}`` of the null temporal scores: with ``empirical``
            (1.0, what ``calibrate`` makes) one window is read from the measured sample ``samples["score_null"]``
            (``EmpiricalTail``), else (made by hand) from a Gaussian through the median and sigma (the 90th
            percentile's); ``held_out``: the share of the frames its pairs were drawn from out of sample (a stream's
            own, ``calibrate``'s ``held_out``; absent: drawn in sample); empty = the score path is off.
        inlier_null: ``{"u", "beta", "empirical", "floor", "samples"}``: the pair null; with ``empirical`` (1.0, what
            ``calibrate`` makes) the measured sample ``samples["hard_inliers"]`` itself
            (``retrieval.decision.EmpiricalTail``), else the exponential ``TailModel(u, beta)`` (made by hand);
            ``floor``: the fewest inliers that count as evidence; empty = no verification, the score path decides.
        tests: ``{"score": pairs, "inliers": pairs}`` the run will test (the NFA's multiplier).
        expected_false_loops: the a-contrario target over the whole run.
        notes: one line per choice, saying why (printed, and kept in the summary).
        descriptor: identity of the global descriptor (weights) it was made with; a run with other weights refuses it.
        fused: ``{"measured" or "u", "beta", "single", "span", "tol", "stretch_cos", "still_cos", "samples"}``: the
            tail of the fused evidence on hard-negative sequences (decades: with ``measured``, ``samples["hard_fused"]``
            as measured, ``retrieval.decision.MeasuredTail``; else a fitted ``TailModel(u, beta)``), the most frames
            fused (``span``), whether one pair may decide alone (1.0) or not
            (0.0), the cosine under which a frame no longer looks like the query, and the one at or above which the
            camera stood still (``retrieval.decision``; a calibration.h5 without it: no stop rule).
        samples: the measured distributions, by name (``random_inliers``, ``hard_inliers`` (the pair null: hard and
            random pairs), ``retrieved_inliers`` (the pairs retrieval returned, each hard sequence's first),
            ``positive_inliers``, ``hard_fused``, ``positive_fused``, ``adjacent_cos``, ``score_null``,
            ``score_fused``): saved in ``calibration.h5``
            under ``samples/``.
        features: the conf of the local features its inlier thresholds were calibrated on
            (``calibrated_features``); a run extracting other ones refuses it (empty: not recorded).
        spans: the score path's fused windows, ``{"window": frames, "measured": 1.0, "span": windows, "speeds":
            [the lines' speeds]}``: the fused evidence of the far-side lines over 1..span windows, the best speed's, is
            ``samples["score_fused"]`` ``(n, span)`` (``retrieval.decision.ScoreSpans``); empty = one window decides.
        seconds: wall time of a fresh calibration, ``{"own": s, "shared": s}``: its own work (edge ratios, whitening,
            nulls, sampled verifications, fits) and the run's work it did ahead (reading and encoding every frame,
            local features the run reuses); empty for a loaded one (not saved).
    """

    edge_reference: float | None = None
    whitening: Whitening | None = None
    score_null: dict[str, float] = field(default_factory=dict)
    inlier_null: dict[str, float] = field(default_factory=dict)
    tests: dict[str, float] = field(default_factory=dict)
    expected_false_loops: float = 0.1
    notes: list[str] = field(default_factory=list)
    descriptor: str = ""
    fused: dict[str, float] = field(default_factory=dict)
    samples: dict[str, np.ndarray] = field(default_factory=dict)
    seconds: dict[str, float] = field(default_factory=dict)
    spans: dict[str, Any] = field(default_factory=dict)
    features: dict[str, Any] = field(default_factory=dict)  #: the local features' conf it was made with (empty:
    #                                                          not recorded: made in memory by hand)
    _tails: dict[str, tuple[np.ndarray, EmpiricalTail]] = field(default_factory=dict, repr=False, compare=False)

    def empirical(self, name: str) -> EmpiricalTail:
        """The ``EmpiricalTail`` of ``samples[name]``, sorted once (a run reads it for every candidate)."""
        arr = self.samples[name]
        kept = self._tails.get(name)
        if kept is None or kept[0] is not arr:  # the sample itself kept: a new one is read again
            kept = (arr, EmpiricalTail(arr))
            self._tails[name] = kept
        return kept[1]

    def far_side_level(self) -> tuple[float, float] | None:
        """``(median, sigma)`` (sigma from the 90th percentile) of the far-side scores of the newest frames a
        stream's fit read, under a whitening fitted on the frames before them (``samples["held_out_far_side"]``,
        ``_out_of_sample``; measured by a stream's fit on the inlier path, ``calibrate``'s ``held_out``): the level
        its drift checks compare the frames after the fit with (``retrieval.online``). None where not measured."""
        scores = self.samples.get("held_out_far_side")
        return score_level(scores) if scores is not None and len(scores) >= MIN_NULL_PAIRS else None

    @property
    def path(self) -> str:
        """``"inliers"`` where local verification decides, ``"score"`` where the global code and temporal
        consistency do (too few local features), ``"none"`` for an empty calibration."""
        return "inliers" if self.inlier_null else "score" if self.score_null else "none"

    def confidence(self, seq_score: float, inliers: int) -> float:
        """``-log10 NFA`` of a candidate on the deciding path (``-inf`` when it has no evidence there)."""
        return float(self.confidences(np.array([seq_score], np.float64), np.array([inliers], np.int64))[0])

    def confidences(self, seq_scores: np.ndarray, inliers: np.ndarray) -> np.ndarray:
        """``confidence`` of ``m`` candidates at once: their temporal scores ``(m,)`` and inlier counts ``(m,)`` ->
        ``(m,)`` float64, the same values (a refit's replay reads tens of thousands)."""
        if self.path == "inliers":
            return self.inlier_confidences(inliers)
        return self.score_confidences(seq_scores)

    @property
    def accept_at(self) -> float:
        """The confidence a loop needs: NFA <= expected_false_loops / 2 on its path."""
        return -math.log10(self.expected_false_loops / 2)

    def score_confidence(self, score: float) -> float:
        """``-log10 NFA`` of one window's temporal score deciding alone (``-inf`` when the score path is off): the
        measured null's empirical p-value (``score_null["empirical"]``, what ``calibrate`` makes), else, for a
        calibration made by hand, a Gaussian through ``score_null``'s median and sigma."""
        return float(self.score_confidences(np.array([score], np.float64))[0])

    def score_confidences(self, scores: np.ndarray) -> np.ndarray:
        """``score_confidence`` of each of ``scores`` ``(m,)`` -> ``(m,)`` float64."""
        n, x = self.score_null, np.asarray(scores, np.float64).reshape(-1)
        if not n:
            return np.full(len(x), -math.inf)
        if n.get("empirical") and "score_null" in self.samples:
            return -(math.log10(self.tests["score"]) + self.empirical("score_null").log10_sfs(x))
        gauss = [gaussian_log10_sf((score - n["median"]) / n["sigma"]) for score in x.tolist()]
        return -(math.log10(self.tests["score"]) + np.array(gauss, np.float64))

    def pair_tail(self) -> TailModel | EmpiricalTail | None:
        """The hard-negative inlier null one pair's evidence is read from: the measured sample itself
        (``EmpiricalTail``, ``inlier_null["empirical"]``: no tail past the sample) or, for a calibration made by hand
        or before, the exponential ``TailModel``; None where verification is off."""
        n = self.inlier_null
        if not n:
            return None
        if n.get("empirical") and "hard_inliers" in self.samples:
            return self.empirical("hard_inliers")
        return TailModel(n["u"], n["beta"])

    def inlier_confidence(self, inliers: int) -> float:
        """``-log10 NFA`` of one inlier count deciding alone (``-inf`` when verification is off, the check did not
        run, or the count is under the floor)."""
        return float(self.inlier_confidences(np.array([inliers], np.int64))[0])

    def inlier_confidences(self, inliers: np.ndarray) -> np.ndarray:
        """``inlier_confidence`` of each of ``inliers`` ``(m,)`` -> ``(m,)`` float64."""
        n, x = self.inlier_null, np.asarray(inliers, np.int64).reshape(-1)
        out = np.full(len(x), -math.inf)
        if not n:
            return out
        ok = (x >= 0) & (x >= n["floor"])
        if ok.any():
            out[ok] = -(math.log10(self.tests["inliers"]) + self.pair_tail().log10_sfs(x[ok].astype(np.float64)))
        return out

    def score_spans(self, filt: TemporalFilter | None, stops: Stops | None = None) -> ScoreSpans | None:
        """The score path's fused windows scored by the run's filter ``filt`` (None where not calibrated); ``stops``:
        the run's (a line at another speed then reads no window through a stop: ``ScoreSpans``)."""
        if not self.spans or filt is None or "score_fused" not in self.samples:
            return None
        fused = np.asarray(self.samples["score_fused"], np.float64).reshape(len(self.samples["score_null"]), -1)
        measured = [MeasuredTail(fused[np.isfinite(fused[:, j]), j]) for j in range(int(self.spans["span"]))]
        return ScoreSpans(filt.score, int(self.spans["window"]), self.empirical("score_null"), measured,
                          self.tests["score"], tuple(self.spans.get("speeds", (1.0,))), stops)

    def decision(self, exclude_recent: int, filt: TemporalFilter | None = None) -> Decision:
        """The run's fused decision (``retrieval.decision``): on the inlier path, and on the score path the fused
        windows scored by ``filt`` (the run's temporal filter), the windows deciding beside the inlier path too where
        their nulls were measured out of sample (``SCORE_BESIDE_INLIERS``); with the trajectory's "too recent" rule
        (``exclude_recent`` frames as its floor)."""
        n, f = self.inlier_null, self.fused
        horizon = Horizon(f["stretch_cos"], exclude_recent) if "stretch_cos" in f else None
        measured = f.get("measured") and "hard_fused" in self.samples
        stops = Stops(f["still_cos"]) if "still_cos" in f else None
        return Decision(self.pair_tail(),
                        MeasuredTail(self.samples["hard_fused"]) if measured else
                        TailModel(f.get("u", 0.0), f.get("beta", 1 / _LN10)), self.tests.get("inliers", 1.0),
                        self.accept_at, bool(f.get("single", 0.0)), horizon, n.get("floor", 0.0),
                        int(f.get("span", SPAN)), int(f.get("tol", TOL)), spans=self.score_spans(filt, stops),
                        stops=stops,
                        speeds=tuple(f.get("speeds", (1.0,))),
                        both=SCORE_BESIDE_INLIERS and bool(self.score_null.get("held_out")))

    def thresholds(self) -> dict[str, float | None]:
        """The smallest temporal score or inlier count that is accepted (None for the path that does not decide)."""
        out: dict[str, float | None] = {"score": None, "inliers": None}
        a = self.accept_at
        if self.path == "score":
            lo, hi = self.score_null["median"], self.score_null["median"] + 100 * self.score_null["sigma"]
            if self.score_confidence(hi) >= a:
                for _ in range(60):
                    mid = (lo + hi) / 2
                    lo, hi = (lo, mid) if self.score_confidence(mid) >= a else (mid, hi)
                out["score"] = hi  # else None: one window never decides alone (a measured null)
        if self.inlier_null:
            x, top = int(self.inlier_null["floor"]), int(self.inlier_null["floor"]) + 100_000
            tail = self.pair_tail()
            if isinstance(tail, EmpiricalTail):  # constant past its largest sample: no need to look further
                top = min(top, max(x, int(tail.x[-1]) if len(tail.x) else x) + 2)
            while self.inlier_confidence(x) < a and x < top:
                x += 1
            out["inliers"] = x if x < top else None  # None: one pair never decides alone (a measured null)
        return out

    def identity(self) -> str:
        """A short text that changes when any choice changes (stored in the keyframe database)."""
        body = json.dumps([self.edge_reference, self.score_null, self.inlier_null, self.tests,
                           self.expected_false_loops, self.fused] + ([self.spans] if self.spans else [])
                          + ([self.features] if self.features else []),
                          sort_keys=True)  # without spans or features: the identity an earlier calibration.h5 had
        h = hashlib.sha256(body.encode() + (self.whitening.identity().encode() if self.whitening else b""))
        return h.hexdigest()[:16]

    def save(self, path: str | Path) -> None:
        """Writes ``calibration.h5`` (temporary file, then rename)."""
        with atomic_write(path, "wb") as f:
            self._write(f)

    def to_bytes(self) -> bytes:
        """The bytes ``save`` writes (the keyframe store keeps a stream's own calibration so: ``retrieval.online``)."""
        buf = io.BytesIO()
        self._write(buf)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, name: str = "calibration") -> "Calibration":
        """The calibration ``to_bytes`` gave (``name`` says where it came from in errors); as ``load``."""
        return cls.load(io.BytesIO(data), name)

    def _write(self, f: Any) -> None:
        """Writes the calibration as HDF5 into the open binary file ``f``."""
        meta = {"edge_reference": self.edge_reference, "score_null": self.score_null,
                "inlier_null": self.inlier_null, "tests": self.tests,
                "expected_false_loops": self.expected_false_loops, "notes": self.notes, "descriptor": self.descriptor,
                "fused": self.fused, "spans": self.spans, "features": self.features}
        with h5py.File(f, "w") as h5:
            h5.attrs["format_version"] = CALIBRATION_FORMAT
            h5.attrs["calibration"] = json.dumps(meta)
            if self.whitening is not None:
                grp = h5.create_group("whitening")
                for key, value in self.whitening.state().items():
                    grp.create_dataset(key, data=value)
            grp = h5.create_group("samples")
            for key, value in self.samples.items():
                grp.create_dataset(key, data=np.asarray(value, np.float64))

    @classmethod
    def load(cls, path: str | Path | io.BytesIO, name: str | None = None) -> "Calibration":
        """Reads ``calibration.h5`` (or the bytes of one: ``from_bytes``).

        Raises:
            DatabaseError: the file cannot be read or is damaged; ConfigError: another format version.
        """
        name = str(path) if name is None else name
        try:
            with h5py.File(path, "r") as h5:
                version = int(h5.attrs["format_version"])
                if version != CALIBRATION_FORMAT:
                    raise ConfigError(f"{name} has format_version {version}; this software reads "
                                      f"{CALIBRATION_FORMAT}: calibrate again")
                meta = json.loads(h5.attrs["calibration"])
                white = None
                if "whitening" in h5:
                    white = Whitening.from_state({k: h5["whitening"][k][()] for k in h5["whitening"]}, name)
                samples = {k: h5["samples"][k][()] for k in h5["samples"]} if "samples" in h5 else {}
        except ConfigError:
            raise
        except (OSError, KeyError, ValueError, TypeError) as err:
            raise DatabaseError(f"cannot read the calibration {name} ({type(err).__name__}); it is damaged: "
                                "move it away to calibrate again") from None
        return cls(meta["edge_reference"], white, meta["score_null"], meta["inlier_null"], meta["tests"],
                   meta["expected_false_loops"], list(meta["notes"]), str(meta.get("descriptor", "")),
                   dict(meta.get("fused", {})), samples, spans=dict(meta.get("spans", {})),
                   features=dict(meta.get("features", {})))


class TooFewFrames(ConfigError):
    """The sequence is too short to calibrate on (``detect`` then falls back to the fixed policy, with a warning)."""


# ------------------------------------------------------------------------------------------------- the calibration
def calibration_frames(n_frames: int, window: int, length: int, max_frames: int) -> np.ndarray:
    """Frame indices the calibration reads: all of them, or contiguous blocks spread over a long sequence.

    Each block holds ``window + length`` frames, enough for the far-side pairs of its last queries.
    """
    if n_frames <= max_frames:
        return np.arange(n_frames)
    block = min(max_frames, window + length + 32)
    starts = np.linspace(0, n_frames - block, max(1, max_frames // block)).astype(int)
    return np.unique(np.concatenate([np.arange(s, s + block) for s in starts]))


def _encode_all(frames: Iterable[tuple[int, np.ndarray | None]], gate: EdgeGate, descriptor: GlobalDescriptor,
                progress: bool, known: dict[int, np.ndarray] | None = None, ratios: dict[int, float] | None = None
                ) -> tuple[dict[int, np.ndarray | None], dict[int, np.ndarray], float, float]:
    """Pass over the frames: edge ratios first (the reference; taken from ``ratios`` where it has them, the frame's
    image then may be None), then codes of the frames that pass the gate (taken from ``known`` where it has them:
    codes computed ahead from the same images); the last value is the seconds spent on edge ratios (the
    calibration's own work: the run measures them again)."""
    known = {} if known is None else known
    given = {} if ratios is None else ratios
    images: dict[int, np.ndarray | None] = {}
    ratios = {}
    gate_s = 0.0
    for fid, image in tqdm(frames, desc="calibrate: read", unit="frame", disable=not progress, leave=False):
        images[fid] = image
        t0 = time.perf_counter()
        ratios[fid] = given[fid] if fid in given else gate.edge_ratio(image)
        gate_s += time.perf_counter() - t0
    reference = float(np.median(list(ratios.values()))) if ratios else 0.0
    gate.reference = reference
    passing = [fid for fid in images if not gate.conf["enabled"] or ratios[fid] >= gate.threshold]
    todo = [fid for fid in passing if fid not in known]  # a bar only for the codes computed here
    encoded = {fid: descriptor(images[fid]) for fid in tqdm(todo, desc="calibrate: encode", unit="frame",
                                                           disable=not progress or not todo, leave=False)}
    codes = {fid: encoded[fid] if fid in encoded else known[fid] for fid in passing}
    return images, codes, reference, gate_s


def _null_scores(ids: np.ndarray, table: CodeTable, filt: TemporalFilter, window: int,
                 moved: np.ndarray | None = None, min_apart: int = 1) -> np.ndarray:
    """``(query, ref, score)`` rows for every far-side pair: ``window // 2 <= query - ref < window``, leaving out
    the pairs whose line passes two frames between which the camera stood still (``moved``: ``(n,)`` bool by position
    in ``ids``, ``camera_moved``): the pair moved back together over the frames its fused score reads (``SPAN`` windows of
    the filter's ``length``) must have moved apart at every step; a pair at one stop is one place, not a pair known
    not to be a loop, and its line would carry that place into the nulls' tails."""
    return _scored(*_null_pairs(ids, filt, window, moved, min_apart), filt, table)


def _scored(q: np.ndarray, r: np.ndarray, filt: TemporalFilter, table: CodeTable) -> np.ndarray:
    """``(query, ref, score)`` rows ``(m, 3)`` of the pairs ``q``, ``r`` ``(m,)``: the filter's scores on ``table``,
    ``PAIR_CHUNK`` pairs a call (the similarities read in bulk; the same scores as one pair at a time)."""
    return np.concatenate([np.zeros((0, 3))] + [
        np.column_stack([q[lo:lo + PAIR_CHUNK], r[lo:lo + PAIR_CHUNK],
                         filt.score(q[lo:lo + PAIR_CHUNK], r[lo:lo + PAIR_CHUNK], table)])
        for lo in range(0, len(q), PAIR_CHUNK)])


def _null_pairs(ids: np.ndarray, filt: TemporalFilter, window: int, moved: np.ndarray | None = None,
                min_apart: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``_null_scores``' pairs, unscored: ``(queries (m,), refs (m,))`` int64, by query then ref ascending."""
    ids = np.asarray(ids, np.int64)
    if not len(ids):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    moves = np.full(int(ids.max()) + 1, -1, np.int64)  # moved frames up to each frame id (-1: not present)
    moves[ids] = np.cumsum(np.ones(len(ids), bool) if moved is None else moved)
    back = np.arange(SPAN * int(filt.conf.get("length", 1)), dtype=np.int64)
    behind = np.arange(window - 1, window // 2 - 1, -1, dtype=np.int64)  # query - ref, the refs ascending
    q, r = np.repeat(ids, len(behind)), (ids[:, None] - behind[None, :]).ravel()
    keep = r >= 0
    q, r = q[keep], r[keep]
    keep = moves[r] >= 0
    q, r = q[keep], r[keep]
    kept = np.zeros(len(q), bool)
    for lo in range(0, len(q), PAIR_CHUNK):  # the lines' frames a chunk at a time: memory bounded
        qs, rs = q[lo:lo + PAIR_CHUNK, None] - back[None, :], r[lo:lo + PAIR_CHUNK, None] - back[None, :]
        mq, mr = moves[np.maximum(qs, 0)], moves[np.maximum(rs, 0)]
        kept[lo:lo + PAIR_CHUNK] = ((rs < 0) | (mq < 0) | (mr < 0) | (mq - mr >= min_apart)).all(1)
    return q[kept], r[kept]


def far_side_scores(ids: np.ndarray, table: CodeTable, filt: TemporalFilter, window: int, moved: np.ndarray,
                    newest: int = 0) -> np.ndarray:
    """``(n,)`` temporal scores of the far-side pairs of keyframes ``ids`` (``window // 2 <= query - ref <
    window``, both in ``ids``; pairs through a stop left out: ``moved (len(ids),)`` bool, False where the camera
    stood still, ``camera_moved`` of the raw codes as a fit reads them; with ``newest``, only those whose query is among
    the ``newest`` last ids): what the nulls are drawn from, for a stream that checks a calibration against its
    newest frames (``retrieval.online``)."""
    ids = np.asarray(ids, np.int64)
    if len(ids) < 2:
        return np.zeros(0)
    rows = _null_scores(ids, table, filt, window, np.asarray(moved, bool))
    if newest and len(rows):
        rows = rows[rows[:, 0] >= ids[-min(newest, len(ids))]]
    return rows[:, 2] if len(rows) else np.zeros(0)


def _reversed_lines(ids: np.ndarray, table: CodeTable, filt: TemporalFilter, window: int, moved: np.ndarray,
                    newest: int) -> tuple[np.ndarray, CodeTable]:
    """The score path's long-range null (module doc, item 3): *reversed* lines between frames far apart, the query's
    frames going back against the reference's going forward (``(q - i, r + i)`` where a revisit's line is
    ``(q - i, r - i)``). A revisit in the direction of travel lies on a forward line, and a reversed one crosses it at
    one frame at most, so every reversed line is known not to be a loop at any distance, where look-alike stretches
    recur (a railway's forest, a corridor's doors) and the far-side pairs, ``window // 2`` to ``window`` frames back,
    do not reach. Each line's frames, over ``SPAN`` windows of the filter's ``length``, stay ``window // 2`` moved
    frames apart, and either both of its sides pass a frame where the camera stood still or neither does (``moved``:
    ``(n,)`` bool by position in ``ids``, ``camera_moved``: a stop is one place, which the other side, passing by
    that place, meets for as long as the stop lasts; Nordland at half resolution, summer's station stops against
    winter passing them: windows as alike as the revisit's); its query is at least ``newest`` (the
    frames the near null's queries are drawn from); at most ``REVERSED_LINES`` of them, a seeded sample. None for a
    filter that also follows reverse revisits (a velocity <= 0), one without lines (``bayes``) or whose window is one
    frame (``none``, a sequence of ``length`` 1: one pair read backwards is the pair itself, a revisit among them).

    Returns:
        ``(rows (m, 3), mirror)``: ``(query, ref, score)`` rows with the ids of ``mirror``, a code table holding frame
        ``k`` at ``off + k`` and, mirrored, at ``off - 1 - k`` (``off`` = the last id + 1), so that the filter's and
        ``ScoreSpans``' forward lines through ``(off + q, off - 1 - r)`` read the reversed ones.
    """
    q, r = _reversed_pairs(ids, filt, window, moved, newest)
    if q is None:
        return np.zeros((0, 3)), table
    off = int(np.asarray(ids).max()) + 1
    tids, codes = table.items()
    mirror = CodeTable.fixed(np.r_[off - 1 - tids[::-1], off + tids], np.r_[codes[::-1], codes])
    return _scored(off + q, off - 1 - r, filt, mirror), mirror


def _reversed_pairs(ids: np.ndarray, filt: TemporalFilter, window: int, moved: np.ndarray,
                    newest: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``_reversed_lines``' lines, unscored: ``(queries (m,), refs (m,))`` int64 in the frames' own ids (a line reads
    ``(q - i, r + i)``), by query then ref; ``(None, None)`` for a filter without reversed lines."""
    ids = np.asarray(ids, np.int64)
    if not isinstance(filt, SequenceFilter) or filt.conf["length"] < 2 or min(filt.conf["velocities"]) <= 0 \
            or len(ids) < 2:
        return None, None
    velocities = filt.conf["velocities"]
    off = int(ids.max()) + 1
    reach = SPAN * int(filt.conf["length"]) - 1  # frames a line reads back from its query
    ahead = int(math.ceil(max(velocities) * reach))  # and forward from its reference
    count = np.zeros(off + 1, np.int64)  # moved frames before each frame id
    count[ids + 1] = np.asarray(moved, np.int64)
    count = np.cumsum(count)
    still = np.zeros(off + 1, np.int64)  # frames before each frame id where the camera stood still
    still[ids + 1] = ~np.asarray(moved, bool)
    still = np.cumsum(still)
    refs = ids[ids + ahead < off]
    queries = ids[(ids >= newest) & (ids - reach >= 0)]
    # a side that passes a stop reads one place: a line is a reversed line where both sides move (or both pass a
    # stop: two stops alike), not where one side's stop meets the other side passing by that place
    ref_stops = still[refs + ahead + 1] > still[refs]
    query_stops = still[queries + 1] > still[queries - reach]
    parts = []
    for side in (False, True):
        qs, rs = queries[query_stops == side], refs[ref_stops == side]
        # a query's references are a prefix of ``rs``: those whose last frame leaves window // 2 moved frames before
        # the query's first (the count of moved frames only grows with the frame id)
        parts.append((qs, rs, np.searchsorted(count[rs + ahead + 1], count[qs - reach] - window // 2, side="right")))
    sizes = [int(n.sum()) for _, _, n in parts]
    total = sum(sizes)
    if not total:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    flat = np.arange(total) if total <= REVERSED_LINES else np.sort(
        np.random.default_rng(0).choice(total, REVERSED_LINES, replace=False))
    picked, first = [], 0
    for (qs, rs, n_refs), size in zip(parts, sizes):
        mine = flat[(flat >= first) & (flat < first + size)] - first
        ends = np.cumsum(n_refs)
        row = np.searchsorted(ends, mine, side="right")  # the query of each drawn pair, then its reference
        picked.append((qs[row], rs[mine - (ends[row] - n_refs[row])]))
        first += size
    q, r = np.concatenate([p[0] for p in picked]), np.concatenate([p[1] for p in picked])
    order = np.lexsort((r, q))
    return q[order], r[order]


def _tail_fit(values: np.ndarray) -> tuple[float, float, float]:
    """Robust ``(median, q90, q90 - median)`` of null samples (up to ~10% of them may be contaminated)."""
    q50, q90 = np.quantile(values, [0.5, 0.9])
    return float(q50), float(q90), float(q90 - q50)


def score_level(scores: np.ndarray) -> tuple[float, float]:
    """``(median, sigma)`` of far-side scores ``(n,)``, sigma read from the 90th percentile (as a Gaussian's, robust
    to a contaminated tail); ``(0, 1e-4)`` for none."""
    if not len(scores):
        return 0.0, 1e-4
    q50, _, spread = _tail_fit(np.asarray(scores, np.float64))
    return q50, max(spread / 1.2816, 1e-4)


def calibrated_features(conf: dict[str, Any]) -> dict[str, Any]:
    """The local features' conf of a calibrated run (the calibration's and the run's, whose inlier thresholds are
    calibrated on them): ``features`` with its longer side ``calibration.features_px``; ``features`` as they are
    where that is None or the extractor does not downscale (``resize_max`` None or absent: full resolution stays
    so). A run with the fixed policy uses ``features``."""
    px, features = conf["calibration"]["features_px"], conf["features"]
    return features if px is None or features.get("resize_max") is None else {**features, "resize_max": px}


def calibrate(frames: Iterable[tuple[int, np.ndarray]], n_frames: int, conf: dict[str, Any],
              descriptor: GlobalDescriptor, filt: TemporalFilter, K: np.ndarray | None = None,
              progress: bool = True, codes: dict[int, np.ndarray] | None = None,
              features: dict[int, Any] | None = None, ratios: dict[int, float] | None = None,
              local: Callable[[int], Any] | None = None, held_out: float = 0.0,
              verified: dict[tuple[int, int], int] | None = None,
              newest_keypoints: float | None = None) -> Calibration:
    """Calibrates on a sequence's frames (see the module doc).

    Args:
        frames: ``(frame_id, image)`` in frame order (``calibration_frames`` says which to give).
        n_frames: frames in the whole sequence (the number of tests grows with it).
        conf: the detector's resolved conf (``retrieval.detector.resolve_conf``).
        descriptor: the global descriptor the run uses (raw codes; the whitening is fitted here).
        filt: the run's temporal filter (its ``score`` is the score path's statistic).
        K: ``(3, 3)`` intrinsics for the geometric check, or None.
        codes: raw codes already computed from the same images (``{frame_id: (dim,)}``, read when the frames are
            encoded, so it may fill while ``frames`` is consumed); the others are encoded here.
        features: a dict that receives the local features extracted for the inlier null (``{frame_id: Features}``),
            for the run to reuse.
        ratios: edge ratios already measured (``{frame_id: ratio}``: a stream calibrating itself,
            ``retrieval.online``); a frame with one may come with its image None when ``codes`` has its code and
            ``local`` gives its local features.
        local: ``local(frame_id) -> Features`` of a frame already seen (a stream's own keyframe features), used
            instead of extracting them from the frames' images.
        verified: ``{(query, ref): inliers}`` of pairs verified before with these frames' features (a stream's
            earlier fits, ``retrieval.online``): not verified again; the pairs verified here are added to it.
        held_out: on the score path, the share of the frames where the camera moved, newest first, that the
            whitening is not fitted on, the score path's nulls drawn from their far-side pairs only
            (``_out_of_sample``: a stream decides frames its whitening has not seen, ``retrieval.online``); 0: fitted
            on every frame, the nulls from every frame (a sequence calibrated before its run).
        newest_keypoints: the median keypoints a frame of the frames the run decides next (a stream's newest ones,
            ``retrieval.online``); where given, it says which path decides (at least ``calibration.min_features``:
            the inlier path) instead of the frames read; None: the frames read say it.

    Raises:
        ConfigError: too few usable frames, or an exclusion window too short to hold null pairs (``TooFewFrames``
            also where ``held_out`` frames hold too few far-side pairs).
    """
    cc, window = conf["calibration"], conf["search"]["exclude_recent"]
    if window < 4:
        raise ConfigError(f"calibration needs search.exclude_recent >= 4 frames (its far side holds the pairs known "
                          f"not to be loops); got {window}. Set calibration.enabled: false to use fixed thresholds")
    t0 = time.perf_counter()
    gate = EdgeGate(conf["gate"])
    images, raw, reference, gate_s = _encode_all(frames, gate, descriptor, progress, codes, ratios)
    shared = time.perf_counter() - t0 - gate_s  # reading and encoding every frame: the run's work, reused
    if len(raw) < max(MIN_FIT_CODES, window):
        raise TooFewFrames(f"calibration needs at least {max(MIN_FIT_CODES, window)} frames that pass the gate; "
                           f"got {len(raw)} of {len(images)}")
    cal = Calibration(expected_false_loops=cc["expected_false_loops"], descriptor=descriptor.identity,
                      features=calibrated_features(conf))
    if gate.conf["mode"] == "relative":
        cal.edge_reference = reference
        cal.notes.append(f"gate: median edge ratio {reference:.3f}; frames under {gate.threshold:.3f} "
                         f"({gate.conf['relative']:g} x median) are gated: {len(images) - len(raw)} of {len(images)}")
    ids = np.array(sorted(raw), np.int64)
    codes = np.stack([raw[i] for i in ids])
    moved = camera_moved(codes, descriptor.still_cos)  # False where the camera stood still (the code did not change)
    cal.whitening = _whitening(conf["whitening"], descriptor, codes, cal.notes, moved)
    normed = cal.whitening.transform(codes) if cal.whitening is not None else codes
    table = CodeTable.fixed(ids, normed)
    null = _null_scores(ids, table, filt, window, moved)
    if len(null) < MIN_NULL_PAIRS:
        raise TooFewFrames(f"calibration found only {len(null)} far-side pairs; give a longer sequence or a larger "
                           "search.exclude_recent")
    n_keyframes = max(len(ids) * n_frames / max(len(images), 1), 2.0)
    cal.tests = {"score": max(n_keyframes, (n_keyframes - window) ** 2 / 2),  # every query against every keyframe
                 "inliers": n_keyframes * conf["search"]["k"] * SPAN}  # every run length 1..span counted
    shared += _inlier_path(cal, conf, images, null, table, K, progress, features, local, verified, newest_keypoints)
    null_table, apart = table, None
    if held_out:  # a stream: it decides frames its whitening was not fitted on, the score path's nulls drawn there
        try:  # (on the inlier path too, where the score path decides beside it: ``Decision``'s ``both``)
            null_table, apart = _out_of_sample(
                cal, conf["whitening"], descriptor, filt, ids, codes, moved, window, held_out,
                "the score path's null" + (" (it decides beside the inlier path) and the level the stream's drift "
                                           "checks compare its newest frames with" if cal.inlier_null else ""))
        except TooFewFrames:
            if not cal.inlier_null:
                raise  # the score path alone: nothing may decide on an in-sample null
        if cal.inlier_null and apart is not None:
            cal.samples["held_out_far_side"] = apart[:, 2]
    # in sample (far apart in moved frames too): the nulls of a sequence calibrated before its run, or of a stream
    # too short to hold frames out (its score path then does not decide); on the inlier path also the level of the
    # run's "above chance" gate, which candidates it verifies (the frames' own, as before the score path decided there)
    in_sample = None
    if apart is None or cal.inlier_null:
        in_sample = _null_scores(ids, table, filt, window, moved, window // 2)
        in_sample = in_sample if len(in_sample) >= MIN_NULL_PAIRS else null
    apart = in_sample if apart is None else apart
    far = None if cal.inlier_null and null_table is table else \
        _reversed_lines(ids, null_table, filt, window, moved, int(apart[:, 0].min()))
    _score_path(cal, apart, filt, null_table, far, tuple(conf["calibration"]["score_speeds"]),
                None if in_sample is None or in_sample is apart else in_sample[:, 2])
    if null_table is not table:
        cal.score_null["held_out"] = float(held_out)
    _stretch(cal, ids, table, moved, descriptor.still_cos)
    for key, value in cal.thresholds().items():
        if value is not None:
            cal.notes.append(f"accept: {key} >= {value:.4g} (expected false loops over the run "
                             f"<= {cal.expected_false_loops:g} / 2)")
    if cal.path == "score" and cal.thresholds()["score"] is None:
        cal.notes.append(f"accept: score: no window alone; {_windows_needed(cal, filt)} (expected false loops over "
                         f"the run <= {cal.expected_false_loops:g} / 2)")
    if cal.path == "inliers" and cal.thresholds()["inliers"] is None:
        cal.notes.append(f"accept: inliers: {_run_needed(cal, conf['search']['exclude_recent'])} (expected false "
                         f"loops over the run <= {cal.expected_false_loops:g} / 2)")
    _timed(cal, len(images), time.perf_counter() - t0, shared)
    for line in cal.notes:
        log.info("calibration: %s", line)
    return cal


def run_needed(cal: Calibration, window: int) -> int | None:
    """The shortest run of frames on one line, each above every null pair (``samples["hard_inliers"]``), that the
    calibration's fused decision accepts (``window``: ``search.exclude_recent``); None where no run of up to its
    ``span`` frames is accepted, or the calibration has no measured pair null (the score path, one made by hand)."""
    hard = cal.samples.get("hard_inliers")
    if not cal.inlier_null or hard is None or not len(hard):
        return None
    dec = cal.decision(window)
    top = dec.evidence(float(hard.max()) + 1)
    choice = math.log10(2 * dec.tol + 1)
    for m in range(max(dec.min_support, 1), dec.span + 1):
        if dec.fused(top, [(d, top - choice) for d in range(1, m)]) >= dec.accept_at:
            return m
    return None


def _run_needed(cal: Calibration, window: int) -> str:
    """``run_needed`` as the notes say it."""
    m = run_needed(cal, window)
    if m is None:
        return f"no pair alone and no run of up to {cal.decision(window).span} frames: verify more pairs " \
               "(calibration.null_pairs)"
    return f"no pair alone; a run of {m} frames on one line, each above every null pair " \
           f"(> {cal.samples['hard_inliers'].max():.0f})"


def _timed(cal: Calibration, n_images: int, total: float, shared: float) -> None:
    """Records the calibration's wall time: its own work apart from the run's work it did ahead (``shared``)."""
    cal.seconds = {"own": total - shared, "shared": shared}
    cal.notes.append(f"calibrated on {n_images} frames in {total:.1f} s: its own work (gate reference, whitening, "
                     f"nulls, verifying the sampled pairs, fitting) {total - shared:.1f} s; reading, encoding and "
                     f"extracting local features the run reuses {shared:.1f} s")


def _stretch(cal: Calibration, ids: np.ndarray, table: CodeTable, moved: np.ndarray,
             ceiling: float = STILL_COS) -> None:
    """The cosine under which a frame no longer looks like the query (the 10th percentile of adjacent frames'), and
    the normalised codes' cosine at which the camera stood still (``_still_cos``): ``retrieval.decision.Horizon``
    and ``Stops``."""
    adj = np.r_[False, np.diff(ids) == 1]
    adjacent = table.pairs(ids[adj], ids[adj] - 1).astype(np.float64)
    cal.samples["adjacent_cos"] = adjacent
    cal.fused["stretch_cos"] = float(np.quantile(adjacent, 0.1)) if len(adjacent) else 1.0
    still = ~moved[adj]
    cal.fused["still_cos"] = _still_cos(adjacent, still, ceiling)
    cal.notes.append(f"too recent: frames within search.exclude_recent, and every frame back to where the code "
                     f"stops looking like the query (cosine < {cal.fused['stretch_cos']:.3f}, the adjacent frames' "
                     "10th percentile)")
    cal.notes.append(f"stops: {int(still.sum())} frames where the camera stood still (normalised cosine to the frame "
                     f"before >= {cal.fused['still_cos']:.3f}); a still query is matched only where the reference "
                     "stood still as long")


def _still_cos(adjacent: np.ndarray, still: np.ndarray, ceiling: float = STILL_COS) -> float:
    """The normalised cosine that best reproduces the raw codes' verdict (``camera_moved``) on the adjacent frames
    (``adjacent`` ``(n,)`` cosines, ``still`` ``(n,)`` bool): the fewest pairs on the wrong side, the lowest such cosine
    (every still pair still where they agree), at most ``ceiling`` (the raw codes' own, ``GlobalDescriptor.still_cos``;
    returned where the camera never stood still)."""
    if not still.any():
        return ceiling
    cand = np.unique(adjacent[still])
    moving = np.sort(adjacent[~still])
    wrong = np.searchsorted(np.sort(adjacent[still]), cand, "left") + len(moving) - np.searchsorted(moving, cand)
    return float(min(cand[int(np.argmin(wrong))], ceiling))


def _whitening(wconf: dict[str, Any], descriptor: GlobalDescriptor, codes: np.ndarray, notes: list[str],
               moved: np.ndarray) -> Whitening | None:
    """The code normalisation (see the module doc); with ``whitening.skip_still``, fitted on the codes of frames
    where the camera moved (``moved``, ``camera_moved``) when there are enough of them."""
    if not wconf["enabled"]:
        notes.append(f"codes: raw {codes.shape[1]}-d cosine (whitening.enabled: false)")
        return None
    carried = getattr(descriptor, "whitening", None)
    if wconf["source"] == "weights" and carried is not None:
        notes.append(f"codes: whitened to {carried.dim}-d by the whitening saved with the weights "
                     f"(fitted on {carried.fitted_on} training images)")
        return carried
    if wconf["source"] == "weights":
        raise ConfigError("whitening.source is 'weights' but the weights carry no whitening; train with "
                          "cae-lcd train (it saves one) or use source 'auto'")
    fit = codes[moved] if wconf["skip_still"] and moved.sum() >= MIN_FIT_CODES else codes
    white = Whitening.fit(fit, wconf["dim"], wconf["shrink"])
    notes.append(f"codes: whitened to {white.dim}-d, fitted on this sequence's {len(fit)} codes "
                 f"(shrink {wconf['shrink']:g}" + (f"; {len(codes) - len(fit)} frames where the camera stood still "
                                                   "left out)" if wconf["skip_still"] else ")"))
    return white


def camera_moved(codes: np.ndarray, still_cos: float = STILL_COS) -> np.ndarray:
    """``(n,)`` bool: False for a code the same as the one before it (cosine >= ``still_cos``, the weights' own
    ``GlobalDescriptor.still_cos``: the camera stood still). Far-side pairs between which the camera stood still are
    one place, not pairs known not to be loops; with ``whitening.skip_still`` the whitening leaves such frames out too
    (a robot waiting at a station would weigh that one place as often as it waited)."""
    unit = codes / np.maximum(np.linalg.norm(codes, axis=1, keepdims=True), 1e-12)
    return np.r_[True, np.einsum("ij,ij->i", unit[1:], unit[:-1]) < still_cos]


def _score_path(cal: Calibration, null: np.ndarray, filt: TemporalFilter, table: CodeTable,
                far: tuple[np.ndarray, CodeTable] | None = None, speeds: tuple[float, ...] = (1.0,),
                level: np.ndarray | None = None) -> None:
    """The score path's nulls, measured (module doc, item 3): the far-side pairs' temporal scores as they are (an
    ``EmpiricalTail``: no p-value below ``1 / (n + 1)``) and, with a filter whose score is the run's (sequence,
    none), the fused evidence of the same pairs' lines over 1..``SPAN`` windows (``retrieval.decision.ScoreSpans``),
    measured per span on the line of each pair at the best of ``speeds`` (the decision's statistic); the run's tests
    counted at every span and speed. ``far``: the long-range reversed lines and their table (``_reversed_lines``),
    which join both nulls. ``score_null``'s median and sigma (90th percentile) only
    describe the far-side pairs (the detector's "above chance" gate for verification; ``level``: other far-side
    scores they describe instead, the inlier path's own frames); no Gaussian tail decides."""
    parts = [(null, table)] + ([far] if far is not None and len(far[0]) else [])
    scores = np.concatenate([rows[:, 2] for rows, _ in parts])
    described = null[:, 2] if level is None else np.asarray(level, np.float64)
    (q50, sigma), q90 = score_level(described), _tail_fit(described)[1]
    tail = EmpiricalTail(scores)
    cal.score_null = {"median": q50, "sigma": sigma, "samples": float(len(scores)), "empirical": 1.0}
    cal.samples["score_null"] = scores
    longer = "" if len(parts) == 1 else (
        f" and {len(far[0])} reversed lines between frames far apart (max {far[0][:, 2].max():.4f}; "
        f"{int((far[0][:, 2] > null[:, 2].max()).sum())} above every far-side pair)")
    own = "" if level is None else f" (the frames' own, in sample: median {q50:.4f}, 90th percentile {q90:.4f})"
    null_q50, null_q90 = score_level(null[:, 2])[0], _tail_fit(null[:, 2])[1]
    cal.notes.append(f"score null: {len(null)} far-side pairs, median {null_q50:.4f}, 90th percentile "
                     f"{null_q90:.4f}, max "
                     f"{null[:, 2].max():.4f}{longer}{own}: one window's empirical p-value, at most "
                     f"{tail.max_evidence:.1f} decades (no tail past the sample); {cal.tests['score']:.3g} pairs "
                     "tested in the run")
    if not isinstance(filt, (SequenceFilter, NoFilter)):
        return
    window = int(filt.conf.get("length", 1))
    spans = ScoreSpans(filt.score, window, tail, [MeasuredTail(np.zeros(0))] * SPAN, 1.0, speeds)
    fused = np.vstack([spans.fused_best(rows[:, 0], rows[:, 1], t) for rows, t in parts])
    cal.samples["score_fused"] = fused
    cal.spans = {"window": float(window), "measured": 1.0, "span": float(SPAN), "speeds": [float(v) for v in speeds]}
    cal.tests["score"] *= SPAN * len(speeds)
    top = [f"{j + 1} window{'s' if j else ''}: max {np.nanmax(fused[:, j]) if np.isfinite(fused[:, j]).any() else 0:.1f}"
           f" of {int(np.isfinite(fused[:, j]).sum())}" for j in range(SPAN)]
    cal.notes.append(
        f"score path: a loop is a run of up to {SPAN} consecutive windows of {window} frames on a line (at "
        f"{', '.join(f'{v:g}x' for v in speeds)} the map's speed), every window "
        f"at least {AGREE:g} decade (above the one-window null's 90th percentile), their evidence summed and read "
        "from the heavier of the Gamma tail (windows of disjoint frames taken as independent) and the fused evidence "
        f"measured on the far-side lines, the best speed's (decades; {', '.join(top)}); {cal.tests['score']:.3g} "
        "tests, every span and speed counted")


def _out_of_sample(cal: Calibration, wconf: dict[str, Any], descriptor: GlobalDescriptor, filt: TemporalFilter,
                   ids: np.ndarray, codes: np.ndarray, moved: np.ndarray, window: int, held_out: float,
                   purpose: str) -> tuple[CodeTable, np.ndarray]:
    """The score path's nulls measured out of sample (issue 27), for a whitening fitted on every frame ``ids (n,)``
    (raw ``codes (n, D)``, ``moved (n,)`` as ``camera_moved``) that decides the frames after them: a second whitening is
    fitted on the frames before the newest ones that hold the share ``held_out`` of the frames where the camera moved
    (a stop holds no null pair), and the nulls are the far-side pairs (far apart in moved frames; ``window``:
    ``search.exclude_recent``) whose query is one of those newest frames, scored under it. A whitening fitted on few
    frames (4 a dimension) makes the frames it was fitted on look less alike than the frames after it, and those are
    the ones a stream decides: measured on the 00-then-07 stress set at 64x32, under a whitening fitted on its first
    320 frames, the far-side pairs' 90th percentile is 0.027 on those frames and 0.061 on the 40 after them, and
    their best window over the whole map has a median of 0.06 and 0.26 (07's frames 121-156 then pass for 00's
    96-130). The second whitening is fitted on fewer frames, so on fewer dimensions (its cosines spread wider) and
    with as many frames a dimension: its frames after the fit stand for the deciding whitening's. Frames in the fit
    (decided again at a refit) face a null higher than their own: a bar only raised. ``purpose`` names what the
    pairs are for in the calibration's note. Returns the code table under the second whitening and the null rows
    (``_held_out_pairs`` scored).

    Raises:
        TooFewFrames: the held-out frames hold fewer than ``MIN_NULL_PAIRS`` far-side pairs.
    """
    cut = _held_out_cut(moved, held_out)
    q, r = _held_out_pairs(ids, filt, window, moved, cut)
    if len(q) < MIN_NULL_PAIRS:
        raise TooFewFrames(f"the newest {len(ids) - cut} frames hold only {len(q)} far-side pairs to measure the "
                           "score path's nulls out of sample")
    white = _whitening(wconf, descriptor, codes[:cut], [], moved[:cut])
    table = CodeTable.fixed(ids, white.transform(codes) if white is not None else codes)
    rows = _scored(q, r, filt, table)
    cal.notes.append(f"out of sample: {purpose} drawn from the far-side pairs of the newest {len(ids) - cut} frames "
                     f"under a whitening fitted on the {cut} before them (the frames a stream decides come after its "
                     "whitening's fit)")
    return table, rows


def _held_out_cut(moved: np.ndarray, held_out: float) -> int:
    """``_out_of_sample``'s split of a fit's frames (``moved (n,)`` as ``camera_moved``): the position of the first
    held-out frame, the frames before it fitting the second whitening; ``n`` where too few moved frames are left to
    fit it."""
    pos = np.flatnonzero(moved)
    keep = len(pos) - int(round(held_out * len(pos)))  # moved frames the second whitening is fitted on
    return int(pos[keep]) if MIN_FIT_CODES <= keep < len(pos) else len(moved)


def _held_out_pairs(ids: np.ndarray, filt: TemporalFilter, window: int, moved: np.ndarray,
                    cut: int) -> tuple[np.ndarray, np.ndarray]:
    """The far-side pairs (far apart in moved frames) whose query is held out (from position ``cut`` of ``ids``,
    ``_held_out_cut``): ``(queries (m,), refs (m,))``, none where nothing is held out."""
    if cut >= len(ids):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    q, r = _null_pairs(ids, filt, window, moved, window // 2)
    keep = q >= ids[cut]
    return q[keep], r[keep]


def windows_needed(cal: Calibration, filt: TemporalFilter) -> int | None:
    """The shortest run of windows on one line, each above every far-side pair, that the score path accepts; 1
    where one window decides (no fused windows with ``filt``), None where no run of up to its span is accepted."""
    spans = cal.score_spans(filt)
    return 1 if spans is None else _shortest_run(spans, cal.accept_at)


def _shortest_run(spans: ScoreSpans, accept_at: float) -> int | None:
    """``windows_needed`` on the score path's fused windows ``spans``."""
    top = spans.tail.max_evidence
    for m in range(1, spans.span + 1):
        if -(math.log10(spans.tests) + fused_log10_sf(m, m * top, spans.measured[m - 1])) >= accept_at:
            return m
    return None


def _windows_needed(cal: Calibration, filt: TemporalFilter) -> str:
    """``windows_needed`` as the notes say it."""
    spans = cal.score_spans(filt)
    if spans is None:
        return "one window decides (no fused windows with this temporal filter)"
    m = _shortest_run(spans, cal.accept_at)
    if m is None:
        return f"no run of up to {spans.span} windows: the far-side sample is too small for the run's tests"
    return f"a run of {m} windows of {spans.window} frames on one line, each above every far-side pair " \
           f"(> {spans.tail.x[-1]:.4f})"


def _extract_side_by_side(fconf: dict[str, Any], images: dict[int, np.ndarray], fids: list[int]) -> dict[int, Any]:
    """Local features of ``images[fid]`` for ``fids``, on every core: one single-threaded extractor per worker
    (``cae_lcd.core.threads``), the same features as one after another."""
    n = min(cpu_count(), max(1, len(fids)))

    def part(chunk: list[int]) -> list[tuple[int, Any]]:
        extractor = create_extractor(fconf)
        return [(fid, extractor.extract(images[fid])) for fid in chunk]

    with ThreadPoolExecutor(n, thread_name_prefix="calibrate-features") as pool:
        return dict(pair for done in pool.map(part, [fids[i::n] for i in range(n)]) for pair in done)


class _Verify:
    """Verifies pairs of calibration frames as the run does (features extracted once per frame, into ``feats``: the
    run reuses them; each pair verified once, its count kept in ``verified``: a stream's refits share it, so a refit
    verifies only the pairs no fit before it verified); thread-safe (one verifier per thread: OpenCV and torch release
    the GIL)."""

    def __init__(self, conf: dict[str, Any], images: dict[int, np.ndarray], K: np.ndarray | None,
                 feats: dict[int, Any], local: Callable[[int], Any] | None = None,
                 verified: dict[tuple[int, int], int] | None = None) -> None:
        self.conf, self.fconf, self.local = conf, calibrated_features(conf), local
        self.min_matches = conf["policy"]["min_matches"]
        self.floor = conf["calibration"]["min_inliers"]  # the checks stop early under it, as the run's do
        self.images, self.K, self.feats = images, K, feats
        self.verified = {} if verified is None else verified  # (query, ref) -> inliers (0 with too few matches)
        self._local = threading.local()
        self.extract_s = 0.0  # wall seconds spent extracting features (work the run reuses)

    def keypoints(self) -> list[int]:
        return [len(f) for f in self.feats.values()]

    def prefetch(self, fids: Iterable[int]) -> None:
        """Extracts the features of ``fids`` (those in the calibration and not extracted yet) on every core."""
        t0 = time.perf_counter()
        todo = sorted({int(f) for f in fids if f in self.images and f not in self.feats})
        self.feats.update({f: self.local(f) for f in todo} if self.local is not None else
                          _extract_side_by_side(self.fconf, self.images, todo))
        self.extract_s += time.perf_counter() - t0

    def __call__(self, q: int, r: int) -> int | None:
        """Inliers of ``(q, r)`` (0 with too few matches): kept from an earlier call, else verified now (a pair's
        count never changes: the same features, the same deterministic check); None where a frame is not in the
        calibration or its features were not extracted (``prefetch`` first)."""
        if q not in self.images or r not in self.images:
            return None
        known = self.verified.get((q, r))
        if known is not None:
            return known
        if q not in self.feats or r not in self.feats:
            return None
        count = self.verified[(q, r)] = self._check(q, r)
        return count

    def _check(self, q: int, r: int) -> int:
        """Verifies ``(q, r)`` (their features extracted) as the run does: a pair whose cheap pre-check (the
        fundamental matrix's inliers, ``verify.geometry``) is under the floor (``calibration.min_inliers``) stops
        there with that count, as the run's candidates do. The decision reads no count under the floor (no
        evidence, ``Decision.evidence``; a p-value only for counts at or above it, which are the full check's), so
        only the notes' medians of the null see it; the hard negatives, mostly under it, cost a third as much.
        Without intrinsics the pre-check is MAGSAC's fundamental matrix and the full check the configured
        estimator's: a count at the floor by one and under it by the other is counted alike here and in the run."""
        if not hasattr(self._local, "verifier"):
            self._local.verifier = create_verifier(self.conf["matcher"], self.conf["geometry"])
        check = self._local.verifier.verify(self.feats[q], [self.feats[r]], self.K, self.min_matches, self.floor,
                                            True)[0]
        return max(check.inliers, 0) if check.matches >= self.min_matches else 0


def _plan(null: np.ndarray, table: CodeTable, picks: np.ndarray, gap: int,
          window: int, span: int = SPAN) -> list[tuple[str, list[tuple[int, int]]]]:
    """The pairs to verify for sampled queries: a random far-side pair, the two far-side keyframes retrieval would
    return (hard negatives, each followed back ``span - 1`` frames: a look-alike sequence), and, for one query in
    ``POSITIVE_EVERY``, a positive sequence (the query and the frame ``gap`` before it, followed back likewise);
    ``(kind, [(query, ref), ...])``, the query's pair first. Hard negatives keep ``window // 10`` frames away from
    the exclusion boundary: a revisit just past it (a place longer than the window) is not a look-alike, and the run
    refuses it as too recent anyway. They are drawn only inside the window (``null``: the far side), where a pair is
    known not to be a loop: beyond it a true revisit would pass for a look-alike (KITTI 90 revisits 75-125 frames
    back) and blind the run."""
    rng = np.random.default_rng(0)  # the same pairs every time: a resumed or repeated calibration agrees
    plan, margin = [], max(1, window // 10)
    for n, q in enumerate(picks.tolist()):
        refs = null[null[:, 0] == q, 1].astype(np.int64)
        inner = refs[q - refs < window - margin]
        hard = inner if len(inner) else refs
        hard = hard[np.argsort(-np.nan_to_num(table.pairs(np.full(len(hard), q), hard), nan=-2.0), kind="stable")]
        rand = int(inner[rng.integers(len(inner))]) if len(inner) else -1
        for name, ref in (("random", rand), ("hard", int(hard[0]) if len(hard) else -1),
                          ("hard2", int(hard[min(1, len(hard) - 1)]) if len(hard) else -1),
                          ("positive", q - gap if n % POSITIVE_EVERY == 0 else -1)):
            if ref >= 0:
                plan.append((name, [(q - j, ref - j) for j in range(1 if name == "random" else span)]))
    return plan


def _samples(plan: list[tuple[str, list[tuple[int, int]]]], verify: _Verify,
             progress: bool) -> dict[str, list[list[int]]]:
    """Inlier counts of the planned sequences (``_plan``) by kind; features of the frames to verify extracted first,
    then each distinct pair verified once (sequences share pairs: the hard negatives of neighbouring queries are
    often one line, and so are their positives; a stream's refits share them too, ``_Verify.verified``), side by
    side on every core (the same counts as one after another). A sequence whose first pair is not in the
    calibration is left out."""
    todo = [p for p in dict.fromkeys(p for _, pairs in plan for p in pairs) if p not in verify.verified]
    verify.prefetch(f for pair in todo for f in pair)
    with ThreadPoolExecutor(min(cpu_count(), max(1, len(todo))), thread_name_prefix="calibrate-verify") as pool:
        for _ in tqdm(pool.map(lambda pair: verify(*pair), todo), desc="calibrate: verify", unit="pair",
                      total=len(todo), disable=not progress, leave=False):
            pass
    out: dict[str, list[list[int]]] = {"random": [], "hard": [], "hard2": [], "positive": []}
    for name, pairs in plan:
        seq = [verify(q, r) for q, r in pairs]
        if seq[0] is not None:
            out[name].append([x for x in seq if x is not None])
    return out


def _hard(got: dict[str, list[list[int]]]) -> np.ndarray:
    """The pair null of ``_samples``' output: every pair of both hard sequences and the random far-side pairs (all
    known not to be loops: a random one may verify higher than what retrieval returns, and the null holds it)."""
    return np.array([x for name in ("hard", "hard2", "random") for seq in got[name] for x in seq], np.float64)


def _fused_samples(seqs: list[list[int]], decision: Decision) -> np.ndarray:
    """The fused evidence ``E`` each sampled sequence would have in the run (exact offsets, no choice)."""
    choice = math.log10(2 * TOL + 1)
    out = []
    for seq in seqs:
        ev = [decision.evidence(x) for x in seq]
        out.append(ev[0] + sum(e - choice for e in ev[1:] if e > choice) if ev[0] > 0 else 0.0)
    return np.asarray(out, np.float64)


def _inlier_path(cal: Calibration, conf: dict[str, Any], images: dict[int, np.ndarray], null: np.ndarray,
                 table: CodeTable, K: np.ndarray | None, progress: bool, feats: dict[int, Any] | None = None,
                 local: Callable[[int], Any] | None = None,
                 verified: dict[tuple[int, int], int] | None = None, newest_keypoints: float | None = None) -> float:
    """Hard negatives, random pairs and positives verified (those in ``verified`` not again); the pair tail, the
    fused tail, whether one pair may decide alone; or verification switched off where local features are too few
    (in the median frame of the random pairs', or ``newest_keypoints``: of the frames the run decides next).
    The local features extracted go into ``feats`` (for the run to reuse; ``local(frame_id)`` gives them where the
    frames' images are not given); returns the seconds spent extracting them."""
    cc = conf["calibration"]
    if cc["verification"] == "off":
        cal.notes.append("verification: off (calibration.verification)")
        return 0.0
    verify = _Verify(conf, images, K, {} if feats is None else feats, local, verified)
    queries = np.unique(null[:, 0]).astype(np.int64)
    n_q = min(len(queries), max(10, cc["null_pairs"] // (1 + 3 * SPAN)))
    picks = queries[np.unique(np.linspace(0, len(queries) - 1, n_q).astype(int))]
    window = conf["search"]["exclude_recent"]
    gap = max(1, window // 25)  # a near neighbour: the same place under the sequence's own motion
    plan = _plan(null, table, picks, gap, window)
    # features enough to verify? Looked at first on every query's random pair (its two frames)
    verify.prefetch(f for name, pairs in plan if name == "random" for pair in pairs for f in pair)
    median_kp = float(np.median(verify.keypoints()))
    deciding = median_kp if newest_keypoints is None else float(newest_keypoints)
    if cc["verification"] == "auto" and deciding < cc["min_features"]:
        whose = "per frame" if newest_keypoints is None else \
            f"in the stream's newest frames, {median_kp:.0f} in the frames read"
        cal.notes.append(f"verification: off, local features too few to verify (median {deciding:.0f} keypoints "
                         f"{whose} < calibration.min_features {cc['min_features']}); loops rest on the normalised "
                         "code and temporal consistency")
        return 0.0  # features the run will not use: not the run's work
    got = _samples(plan, verify, progress)
    hard = _hard(got)
    tail = EmpiricalTail(hard)
    cal.inlier_null = {"u": tail.u, "beta": 0.0, "empirical": 1.0, "floor": float(cc["min_inliers"]),
                       "samples": float(len(hard))}
    cal.samples["hard_inliers"] = hard
    dec = Decision(tail, TailModel(0.0, 1 / _LN10), cal.tests["inliers"], cal.accept_at, False,
                   floor=cc["min_inliers"])
    hard_e = _fused_samples(got["hard"] + got["hard2"], dec)
    pos_e = _fused_samples(got["positive"], dec)
    rand = np.array([s[0] for s in got["random"]], np.float64)
    pos = np.array([s[0] for s in got["positive"]], np.float64)
    cal.fused = {"measured": 1.0, "single": 0.0, "span": float(SPAN), "tol": float(TOL),
                 "samples": float(len(hard_e)), "speeds": [float(v) for v in cc["speeds"]]}
    first = np.array([seq[0] for name in ("hard", "hard2") for seq in got[name]], np.float64)
    cal.samples.update({"random_inliers": rand, "positive_inliers": pos, "hard_fused": hard_e,
                        "positive_fused": pos_e, "retrieved_inliers": first})
    q = (lambda x: "none" if not len(x) else f"median {np.median(x):.0f}, 90th percentile "
         f"{np.quantile(x, 0.9):.0f}, max {np.max(x):.0f}")
    cal.notes.append(f"inliers (median {median_kp:.0f} keypoints per frame): random far-side pairs ({len(rand)}): "
                     f"{q(rand)}; null pairs, hard and random ({len(hard)}, {window // 2}-"
                     f"{window - max(1, window // 10)} frames back): {q(hard)}; "
                     f"positives (frames {gap} apart, {len(pos)}): {q(pos)}")
    cal.notes.append(f"pair evidence: the hard negatives' own empirical p-value, at most {tail.max_evidence:.1f} "
                     f"decades a pair (no tail past the sample): a loop needs a run of frames on one line; fused "
                     f"evidence of up to {SPAN} frames (decades): hard-negative sequences median "
                     f"{np.median(hard_e):.1f}, max {hard_e.max():.1f}; positive sequences median "
                     f"{np.median(pos_e):.1f}")
    return verify.extract_s
