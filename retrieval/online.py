"""Calibration as part of the stream (issue 27): a ``LoopDetector`` without a calibration calibrates itself from the
frames it has seen, and a carried calibration is a prior checked against the stream before it decides anything.

The calibration is ``retrieval.calibrate.calibrate`` itself, run on the stream's own frames: the codes, edge ratios
and local features the detector computed anyway (``OnlineCalibration.record``; at most ``calibration.max_frames``
of them read, blocks spread as ``calibration_frames`` chooses), so a refit encodes nothing again. The schedule:

- **Warm-up**: nothing is accepted (nothing verified) until the stream holds ``WARM_UP`` exclusion windows of
  keyframes (``2 * search.exclude_recent``, at least ``MIN_FIRST_FIT``: the far side of the window, where the nulls
  come from, is then seen by half of the frames).
- **Refits at doublings** of the keyframes seen (amortised: the frames a refit reads sum to at most twice the
  stream), each counting the tests of a run of ``max(2 n, calibration.max_frames)`` frames (the next refit's
  length, and never fewer than a long calibration counts: a young calibration, its whitening fitted on few frames,
  claims less; on Nordland this took the stream's false loops from 64 to 19 at the same recall);
- **Checks in between**, every ``CHECK_EVERY`` keyframes: the far-side temporal scores of the newest half window
  of keyframes (``retrieval.calibrate.far_side_scores`` under the calibration's whitening) against the level the
  calibration measured; more than ``DRIFT_Z`` of its sigmas above (a new condition: winter after summer, a
  whitening fitted on too few frames) and the stream is refitted at once (on Nordland's summer -> winter the check
  sees winter 60 frames after it starts: 7 sigma). On the inlier path the level is measured as the checked frames
  are, out of sample (``Calibration.far_side_level``: the fit's newest frames under a whitening fitted on the frames
  before them): in sample, the fit's own frames scatter less than the frames after it (KITTI 00's first fit: sigma
  0.06 against 0.14), and a stream without a revisit was refitted every 30 keyframes (KITTI 00 at 130, 160 and
  190 keyframes; now once, at 150; 21.6 -> 17.3 ms a frame). On the score path, where the codes are the only
  evidence, the level stays the fit's own frames' (the stricter check: measured out of sample there too, Nordland
  gave 2 false loops, precision 0.995).
- **A path the newest frames cannot take**: at each check on the inlier path, where at least ``MIN_VERIFIED`` of
  the newest half window's frames were verified (their local features extracted as they came) and their median
  keypoints are under ``calibration.min_features``, the stream is refitted at once, and every fit chooses its path
  on those newest frames where there are enough of them (``calibrate``'s ``newest_keypoints``), not on all the frames
  it reads: a night revisit of a day's map has a day's keypoints in most of them. A refit onto the other path is
  adopted whatever its null's size (the rule below compares a path with itself). Measured: KITTI 90 at 160x120 with
  its second pass darker (``bench.aliasing.DARKER``, 17 keypoints a frame), its first 190 frames streamed (the refit
  at 200 keyframes, which switched the 200-frame set, never comes): 0 loops before, now refitted onto the score path
  at 120 keyframes, precision 1.000, recall 0.989.
- **A carried calibration** (``LoopDetector(calibration=...)``) is checked the same way at the end of the warm-up,
  on every far-side pair of the warm-up (against its null's median and sigma, ``Calibration.score_null``): where it
  agrees it decides (the warm-up's frames decided again, as after a refit), where it does not the stream refits
  (one log line either way); where the stream is still too short to fit, nothing is accepted (refused). A carried
  calibration kept is then checked and refitted like the stream's own.
- **The score path** (where local features are too few to verify, e.g. 64x32) decides from the stream's own fit,
  its nulls drawn **out of sample** (``HELD_OUT``, ``retrieval.calibrate.calibrate``'s ``held_out``): the far-side
  pairs of the newest quarter of the frames a fit reads, scored under a second whitening fitted on the frames before
  them. A stream decides frames that come after its whitening's fit, and a whitening fitted on few frames (4 a
  dimension) makes the frames it was fitted on look less alike than those after it: with the nulls drawn in sample
  (the frames the whitening was fitted on), KITTI 00 then 07 at 64x32 gave 36 false loops (07's frames 121-156, the
  stream's 321-356, on 00's 96-130, all after the fit at 320 keyframes: under that whitening their windows read 0.26,
  0.22, 0.20 against a far-side null whose largest was 0.20; the 40 frames after the fit have a best window over the
  map of median 0.26, the frames in it 0.06); out of sample, the null's median window is 0.16, its largest 0.49, and
  none is accepted. The decision stays the one fitted on every frame read (its whitening, stops and horizon): frames
  in the fit, decided again at a refit, face a null higher than their own, a bar only raised. Measured (``python -m
  bench.aliasing``, online / offline recall, precision 1.000 on both): KITTI 90 at 64x32 1.000 / 1.000, Nordland
  0.882 / 0.914 (carried from its summer half: 0.882); 0 loops on 00 then 07 at 64x32. Before, the score path
  decided online only from a carried calibration (``SCORE_PATH_DECIDES`` off: recall 0.000 on both); with it on and
  the nulls in sample, a Gaussian score null gave Nordland 22 false loops of 490 and the 64x32 stress set 89.
- **Beside the inlier path, the score path decides too** (``retrieval.calibrate.SCORE_BESIDE_INLIERS``): a fit on
  the inlier path draws the score path's nulls out of sample as above (they are also the level the drift checks
  read), and the decision accepts a run of windows as it would on the score path alone, each path on its own budget.
  Keypoints enough in number need not verify: KITTI 90 at 160x120 with its second pass dark under heavy noise
  (``bench.aliasing.NOISIER``) keeps the inlier path (keypoints of noise) and found none of its revisit on it; now
  precision 1.000, recall 0.980, and every other set as before.
- **A refit never loosens without measured evidence**: it replaces the calibration where its null holds at least as many
  measured samples (the verified hard-negative pairs on the inlier path, the far-side pairs drawn out of sample on the
  score path: a carried calibration's null, drawn in sample, counts none there) as the one it replaces (on the same
  path), or, holding fewer, where a loop under it still needs a run at least as long (``no_shorter_run``: frames on one
  line, ``retrieval.calibrate.run_needed``; windows on one line, ``windows_needed``): its own promise (expected false
  loops over the run) rests on its own samples either way, and the run is the unit that promise is kept in; a thinner
  null that would accept a shorter run is refused and the current calibration kept (one log line). Its tests only grow.
  Why the run and not the bare count: once the fits read ``calibration.max_frames`` frames their nulls hover around one
  size, and a refit refused for holding 0.1-4 % fewer samples kept a decision fitted 60 frames into a new season for 150
  frames (Nordland's winter at half resolution with a snapshot of step 4's training: each window above 0.778 from 560 to
  710 keyframes, recall 0.854; with the run rule 0.902; Nordland streamed 0.960 -> 0.982, carried from its summer half
  0.960 -> 0.982, precision 1.000 and no loop on any stress set either way, ``python -m bench.aliasing``).
- **Loops found late**: after a refit the frames recorded since the start (the newest ``calibration.max_frames`` of
  them in a longer stream: the refit's cost stays bounded, older frames keep their decisions) are decided again
  under the new decision (their candidates' scores recomputed in the new code space; the candidates not verified
  yet that could pass now verified, of the frames not yet a loop: a loop is reported once, so more evidence there
  finds nothing new), and the loops not reported yet are reported as delayed loops (``FrameResult.confirmed``).

Cost: the fits, almost all of it verifying the null's sampled pairs (a SIFT match and a RANSAC check each, about 4 ms
of one core for a full check; ``calibration.null_pairs`` planned a fit), on the frame that triggers the fit. What
keeps it down (the loops, the counts at or above the floor and so the decisions unchanged; ``retrieval.calibrate``):

- **a pair is verified once in a stream** (``OnlineCalibration.verified``: its inliers kept; a fit's sequences share
  pairs, the hard negatives of neighbouring queries often one line and their positives too, and a refit plans again
  pairs an earlier fit verified): KITTI 90 verified 2400 pairs in its two fits, 1304 since (638 at 100 keyframes,
  666 new at 200);
- null pairs are checked as the run checks its candidates: under the floor (``calibration.min_inliers``) the
  geometric pre-check's count stands (no mirror test, no essential matrix), and the hard negatives are mostly there;
- the keyframes of the warm-up have their local features extracted ahead by the detector's feature worker (the first
  fit verifies pairs across all of them), and a refit's late checks of the recorded frames' candidates run pair by
  pair on the verify worker's thread and the caller's (``LoopDetector._verify_late``);
- no late check of a frame already a loop: on KITTI 90 the refit at 200 keyframes checked 340 such pairs (the other
  candidates along the revisit: 1 s of its 1.5 s) and found no loop with them.

The detector's own verified candidates are never among the fits' pairs (beyond the exclusion window; the nulls lie
inside it). Measured (2 cores shared with other work, the code before and after alternately in one run, at the
lightest load): KITTI 90 45 -> 24 ms a frame with the fits amortised (median 14 ms either way; worst frame, the
refit at 200 keyframes, 3.3 -> 1.5 s), 14.7 -> 8.3 s of CPU; KITTI 00 25.9 -> 8.5 s of CPU; then no late check of
a loop's frame, with the code table's rows found by bisection (``retrieval.temporal.CodeTable``): 24.4 -> 20.4 ms a
frame, worst frame 1.4 -> 0.8 s (alternated, 2 runs each). What is left at a refit: about 0.6 s verifying its new
pairs on both cores. Not tried: the fit off the frame path
(a background fit adopted later, the current decision deciding meanwhile; its seconds of CPU beside a stream that
keeps one core busy would land the new decision tens of frames late, and KITTI 90's refit at 200 keyframes, on its
last frame, would never be adopted in the stream), and fewer pairs (the null's size bounds what one pair may claim).

Memory: per keyframe its raw code (float16: 8 kB for the 4096-d CAE code, so 0.8 GB at 100k keyframes; a refit moves
every keyframe into the new whitening from them) and edge ratio, its candidates' ids, matches and inliers, and the
inliers of every pair a fit verified (about 650 new ones a fit; not persisted: a resumed run verifies them again, the
same counts); the local features come from the detector (kept, or extracted again from its grey copy).

Persisted: a detector with a keyframe store (``database``: ``cae-lcd detect``, the API given one, and each of the
fleet's per-robot detectors, which calibrate online too: ``cae_lcd.fleet.recognition``) stores each keyframe's raw
code there (``LoopDetector.calibrates_online``; ``FrameResult.code`` gives it to a memory of its own, the fleet's,
that keeps one fixed code space while the stream's moves), and the state here after each fit (``to_state``: the
calibration, the schedule, the candidates as refits verified them, which frames were reported;
``KeyframeDatabase.write_online``); a resumed run takes the newest state its stored frames reach (``from_state``)
and replays the frames after it (``LoopDetector._load``), so it decides on as the uninterrupted run would have.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from .calibrate import (MIN_NULL_PAIRS, Calibration, TooFewFrames, calibrate, calibration_frames, camera_moved,
                        far_side_scores, run_needed, score_level, windows_needed)
from .descriptors import GlobalDescriptor
from .temporal import CodeTable, TemporalFilter, create_filter

__all__ = ["OnlineCalibration", "Seen", "no_shorter_run", "WARM_UP", "DRIFT_Z", "CHECK_EVERY", "MIN_FIRST_FIT",
           "HELD_OUT", "SCORE_PATH_DECIDES", "MIN_VERIFIED"]

log = logging.getLogger(__name__)

WARM_UP = 2  #: exclusion windows of keyframes before the first fit (nothing accepted until then)
DRIFT_Z = 1.0  #: the newest far-side scores this many of the calibration's sigmas above its null: refit now
MIN_FIRST_FIT = 40  #: the fewest keyframes a first fit reads (a short window's far side holds few pairs)
SCORE_PATH_DECIDES = True  #: whether a stream-fitted calibration on the score path (too few local features to
#   verify: no geometric veto) may decide; False: only a carried calibration that agrees with the stream decides
#   there. On since its nulls are drawn out of sample (``HELD_OUT``; the module doc has the figures before and after)
HELD_OUT = 0.25  #: on the score path, the share of the frames a fit reads (those where the camera moved), newest
#   first, whose far-side pairs are the nulls, scored under a whitening fitted on the frames before them (0: the
#   nulls in sample, from every frame read: on the 64x32 stress set 36 false loops, frames after the fit)
CHECK_EVERY = 10  #: keyframes between two checks of the calibration against the newest frames
MIN_VERIFIED = 5  #: verified frames among the newest half window before their keypoints choose the path
#   (``OnlineCalibration.newest_keypoints``)


@dataclass
class Seen:
    """One recorded keyframe: its candidates ``refs (k,)``, ``matches (k,)`` and ``inliers (k,)`` (-1: not
    verified), and whether a loop was reported for it (the frame's own, or a delayed one)."""

    frame_id: int
    refs: np.ndarray
    matches: np.ndarray
    inliers: np.ndarray
    reported: bool


class OnlineCalibration:
    """The stream's state needed to calibrate it, and the schedule (see the module doc).

    Args:
        conf: the detector's resolved conf.
        prior: a carried calibration (checked at the end of the warm-up), or None.
    """

    def __init__(self, conf: dict[str, Any], prior: Calibration | None = None) -> None:
        self.conf, self.window = conf, conf["search"]["exclude_recent"]
        self.calibration = prior
        self.unchecked = prior is not None  #: a carried calibration not yet checked against the stream
        self.ready = False  #: whether the current calibration may decide (fitted here, or a prior that agreed)
        self.codes: dict[int, np.ndarray] = {}  # raw codes (float16) of every keyframe
        self.ratios: dict[int, float] = {}
        self.seen: list[Seen] = []
        self.verified: dict[tuple[int, int], int] = {}  # (query, ref) -> inliers of every pair a fit verified: a
        #                                                 refit verifies only the pairs no fit before it did
        self._index: dict[int, int] = {}  # frame id -> position in ``seen``
        self.next_fit = max(WARM_UP * self.window, MIN_FIRST_FIT)
        self.next_check = self.next_fit
        self.level: tuple[float, float] | None = None  # (median, sigma) of the far-side scores it was fitted on
        if prior is not None and "sigma" in prior.score_null:
            self.level = (prior.score_null["median"], prior.score_null["sigma"])

    def record(self, frame_id: int, ratio: float, code: np.ndarray, refs: np.ndarray, matches: np.ndarray,
               inliers: np.ndarray, reported: bool) -> None:
        """Keeps a processed keyframe (raw ``code (D,)``, edge ratio, its candidates as decided)."""
        self.codes[frame_id] = np.asarray(code, np.float16)
        self.ratios[frame_id] = float(ratio)
        self._index[int(frame_id)] = len(self.seen)
        self.seen.append(Seen(frame_id, np.asarray(refs, np.int64), np.asarray(matches, np.int64),
                              np.asarray(inliers, np.int64), reported))

    def mark(self, frame_ids: list[int]) -> None:
        """Records that loops were reported for ``frame_ids`` (delayed ones: reported once)."""
        for f in frame_ids:
            i = self._index.get(int(f))
            if i is not None:
                self.seen[i].reported = True

    def reported(self, frame_id: int) -> bool:
        """Whether a loop was reported for keyframe ``frame_id``."""
        i = self._index.get(int(frame_id))
        return i is not None and self.seen[i].reported

    def due(self) -> str | None:
        """``"fit"`` at the end of the warm-up and at each doubling, ``"check"`` between them, else None."""
        n = len(self.seen)
        if n >= self.next_fit:
            return "fit"
        if self.ready and n >= self.next_check:
            self.next_check = n + CHECK_EVERY
            return "check"
        return None

    def raw(self) -> tuple[np.ndarray, np.ndarray]:
        """``ids (n,)`` ascending and their raw codes ``(n, D)`` float32."""
        ids = np.array(sorted(self.codes), np.int64)
        return ids, np.stack([self.codes[int(i)] for i in ids]).astype(np.float32)

    def to_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """The state a resumed run needs besides each keyframe's raw code and edge ratio (which its store keeps):
        ``(meta, arrays)`` for ``KeyframeDatabase.write_online``; ``from_state`` takes it back."""
        meta = {"unchecked": self.unchecked, "ready": self.ready, "next_fit": self.next_fit,
                "next_check": self.next_check, "level": None if self.level is None else list(self.level)}
        seen = self.seen
        cat = (lambda key: np.concatenate([getattr(s, key) for s in seen]).astype(np.int64) if seen
               else np.zeros(0, np.int64))
        arrays = {"frame_id": np.array([s.frame_id for s in seen], np.int64),
                  "counts": np.array([len(s.refs) for s in seen], np.int64), "refs": cat("refs"),
                  "matches": cat("matches"), "inliers": cat("inliers"),
                  "reported": np.array([s.reported for s in seen], bool),
                  "calibration": np.frombuffer(self.calibration.to_bytes() if self.calibration is not None else b"",
                                               np.uint8)}
        return meta, arrays

    def from_state(self, meta: dict[str, Any], arrays: dict[str, np.ndarray], codes: dict[int, np.ndarray],
                   ratios: dict[int, float]) -> None:
        """Takes back ``to_state``'s state, with the raw ``codes`` ``{frame_id: (D,)}`` and edge ``ratios`` of its
        keyframes (from the store).

        Raises:
            KeyError: a keyframe of the state has no raw code or edge ratio.
        """
        self.unchecked, self.ready = bool(meta["unchecked"]), bool(meta["ready"])
        self.next_fit, self.next_check = int(meta["next_fit"]), int(meta["next_check"])
        self.level = None if meta["level"] is None else (float(meta["level"][0]), float(meta["level"][1]))
        blob = np.asarray(arrays["calibration"], np.uint8).tobytes()
        self.calibration = Calibration.from_bytes(blob, "the stored online calibration") if blob else None
        ends = np.cumsum(arrays["counts"])
        self.codes, self.ratios, self.seen, self._index = {}, {}, [], {}
        for fid, reported, lo, hi in zip(arrays["frame_id"].tolist(), arrays["reported"].tolist(),
                                         (ends - arrays["counts"]).tolist(), ends.tolist()):
            self.record(fid, ratios[fid], codes[fid], arrays["refs"][lo:hi], arrays["matches"][lo:hi],
                        arrays["inliers"][lo:hi], bool(reported))

    def drift(self, table: CodeTable, filt: TemporalFilter, still_cos: float, newest: int | None = None) -> float:
        """How far (in the calibration's sigmas) the far-side scores of the ``newest`` keyframes (default: half a
        window; 0: every keyframe seen, a carried calibration's check at the end of the warm-up) lie above the level
        the calibration measured (``table``: the codes as searched, under its whitening; pairs through a stop, raw
        codes ``still_cos`` alike, left out as a fit leaves them); ``inf`` without a level."""
        if self.level is None:
            return float("inf")
        hold = max(self.window // 2, 1) if newest is None else newest
        ids = np.array([s.frame_id for s in (self.seen[-(self.window + hold):] if hold else self.seen)], np.int64)
        scores = far_side_scores(ids, table, filt, self.window, self._moved(ids, still_cos), newest=hold)
        if len(scores) < MIN_NULL_PAIRS:
            return 0.0
        return float((np.median(scores) - self.level[0]) / max(self.level[1], 1e-6))

    def newest_keypoints(self, local: Callable[[int], Any]) -> float | None:
        """The median keypoints of the frames among the newest half window (the frames ``drift`` reads) whose
        candidates were verified (their local features extracted as they came; ``local(frame_id)`` gives them): the
        frames the stream decides next stand for; None where fewer than ``MIN_VERIFIED`` of them were verified (a
        stretch with no revisit verifies little: it says nothing then)."""
        fids = [s.frame_id for s in self.seen[-max(self.window // 2, 1):] if len(s.inliers) and s.inliers.max() >= 0]
        if len(fids) < MIN_VERIFIED:
            return None
        return float(np.median([len(local(f)) for f in fids]))

    def unverifiable(self, local: Callable[[int], Any]) -> float | None:
        """``newest_keypoints`` where the calibration decides on the inlier path (``verification: auto``) and they
        are fewer than ``calibration.min_features``: the newest frames cannot be verified (a revisit at night after a
        day's map), and the stream is refitted at once, its path chosen on them; else None."""
        cc = self.conf["calibration"]
        if self.calibration is None or self.calibration.path != "inliers" or cc["verification"] != "auto":
            return None
        kp = self.newest_keypoints(local)
        return kp if kp is not None and kp < cc["min_features"] else None

    def fit(self, descriptor: GlobalDescriptor, K: np.ndarray | None,
            local: Callable[[int], Any]) -> Calibration | None:
        """Calibrates on the frames seen (``retrieval.calibrate.calibrate``: the codes and edge ratios recorded,
        ``local(frame_id)`` their local features; the path chosen on the newest frames where enough of them were
        verified, ``newest_keypoints``); the new calibration, or None where the current one is kept (too few frames,
        or a null thinner than the current one's on the same path: the rule in the module doc). Schedules the next
        fit."""
        n = len(self.seen)
        self.next_fit = 2 * n
        self.next_check = n + CHECK_EVERY
        c = self.conf
        picks = calibration_frames(n, self.window, c["temporal"].get("length", 1), c["calibration"]["max_frames"])
        ids = [self.seen[int(i)].frame_id for i in picks]
        codes = {f: self.codes[f].astype(np.float32) for f in ids}
        old = self.calibration if self.ready else None
        at_least = 0 if old is None else _null_size(old)
        try:
            cal = calibrate(((f, None) for f in ids), max(2 * n, c["calibration"]["max_frames"]), c, descriptor,
                            create_filter(c["temporal"]), K, False, codes, {}, {f: self.ratios[f] for f in ids}, local,
                            HELD_OUT, self.verified, self.newest_keypoints(local))
        except TooFewFrames as err:
            log.info("online calibration at %d keyframes: not yet (%s)", n, err)
            return None
        samples = _null_size(cal)
        if samples < at_least and cal.path == old.path and not no_shorter_run(cal, old, c):
            log.info("online calibration at %d keyframes: refit kept the current decision (its null holds %d "
                     "samples, the current one %d, and would accept a shorter run: a refit never loosens without "
                     "measured evidence)", n, samples, at_least)
            return None
        thr = {k: round(v, 4) for k, v in cal.thresholds().items() if v is not None}
        log.info("online calibration at %d keyframes (%d read): %s path, null of %d samples, accept %s; next fit "
                 "at %d", n, len(ids), cal.path, samples, thr or "runs of frames", self.next_fit)
        return cal

    def adopt(self, cal: Calibration, table: CodeTable, filt: TemporalFilter, still_cos: float) -> bool:
        """Makes ``cal`` the stream's calibration; its level is measured on the stream's far-side pairs (``table``:
        the codes already moved into its whitening; stops as ``drift`` reads them). It decides (``ready``, returned)
        on the inlier path, and on the score path only with ``SCORE_PATH_DECIDES`` (else nothing is accepted: one
        log line)."""
        self.calibration, self.ready = cal, cal.path == "inliers" or SCORE_PATH_DECIDES
        if not self.ready:
            log.info("online calibration at %d keyframes: the score path (too few local features to verify) decides "
                     "nothing from a calibration fitted on the stream (retrieval.online.SCORE_PATH_DECIDES)",
                     len(self.seen))
        self.level = cal.far_side_level()  # out of sample, as the frames the checks read (the inlier path)
        if self.level is None:  # the score path: in sample, the stricter check (the codes are its only evidence)
            ids = np.array([s.frame_id for s in self.seen], np.int64)
            ids = ids[-min(len(ids), self.conf["calibration"]["max_frames"]):]
            self.level = score_level(far_side_scores(ids, table, filt, self.window, self._moved(ids, still_cos)))
        return self.ready

    def _moved(self, ids: np.ndarray, still_cos: float) -> np.ndarray:
        """``(len(ids),)`` bool: False where the camera stood still (``camera_moved`` of their raw codes, as a fit
        reads them)."""
        return camera_moved(np.stack([self.codes[int(i)] for i in ids]).astype(np.float32), still_cos) if len(ids) \
            else np.zeros(0, bool)


def no_shorter_run(new: Calibration, old: Calibration, conf: dict[str, Any]) -> bool:
    """Whether a loop under ``new`` needs a run at least as long as under ``old`` (same path: frames on one line on
    the inlier path, ``run_needed``; windows on one line on the score path, ``windows_needed``; no run accepted
    counts as the longest); False across paths. ``conf``: the detector's resolved conf."""
    if new.path != old.path:
        return False
    if new.path == "inliers":
        runs = [run_needed(cal, conf["search"]["exclude_recent"]) for cal in (new, old)]
    else:
        filt = create_filter(conf["temporal"])
        runs = [windows_needed(cal, filt) for cal in (new, old)]
    longest = [math.inf if m is None else m for m in runs]
    return longest[0] >= longest[1]


def _null_size(cal: Calibration) -> int:
    """Measured samples of the deciding null that speak for the frames a stream decides: verified pairs on the
    inlier path; on the score path, far-side pairs drawn out of sample (``HELD_OUT``), and none for a null drawn in
    sample (a carried calibration's: the stream's frames all come after its whitening's fit, and an in-sample null
    understates their scores; kept, it let through 19 false loops on Nordland's winter once the stream's refits were
    measured against its 4516 samples)."""
    if cal.inlier_null:
        return int(cal.inlier_null.get("samples", 0))
    return int(cal.score_null.get("samples", 0)) if cal.score_null.get("held_out") else 0
