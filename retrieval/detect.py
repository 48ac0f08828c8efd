"""Offline detection over a sequence (the same path as ``LoopDetector.process``), writing a run folder
(``retrieval.run_folder``): ``conf.yaml``, ``calibration.h5``, ``keyframes.h5``, ``loops.csv``, ``candidates.csv``,
``summary.json`` and the loops' relative poses for a back end (``loop_edges.g2o/.csv/.json``, ``retrieval.edges``).

By default (``calibration.online``) the run calibrates itself as it streams, exactly as ``LoopDetector.process`` does
through the API (``retrieval.online``: a warm-up that accepts nothing, then the whitening, the nulls and the thresholds
fitted from the frames seen and refitted at doublings; loops found late by a refit are written as delayed loops): the
offline result and the streaming result are the same algorithm, and a killed run resumes from the online state kept
in its keyframe store. With ``calibration.online: false`` (``--lookahead``) a calibration pass first looks at the whole
sequence (``retrieval.calibrate``: the gate's reference, the code normalisation and the acceptance thresholds for this
camera, saved as ``calibration.h5``; a resumed run reuses it) and the run decides with it fixed.

A bad frame (unreadable, too small, of a dtype we cannot use) is skipped with a one-line warning naming the file,
keeps its frame id and is counted. A killed run resumes from its database; a database made from other images
(another folder, a file added or removed in the middle) is refused, so frame ids never shift silently.
"""

from __future__ import annotations

import functools
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from cae_lcd.core.conf import ConfigError, dump_conf
from cae_lcd.core.errors import ImageError
from cae_lcd.core.files import prepare_out_dir
from cae_lcd.core.progress import Counted, progress_bar
from cae_lcd.core.threads import apply_thread_policy, cpu_count

from verify.camera import CameraModel, camera_from_options

from .calibrate import Calibration, TooFewFrames, calibrate, calibrated_features, calibration_frames
from .database import KeyframeDatabase
from .descriptors import GlobalDescriptor, create_descriptor
from .detector import KEPT_GEOMETRIES, STAGES, LoopDetector, resolve_conf
from .edges import PosesAhead, check_edge_frame, edge_features, loop_edges, metric_edges, serialised
from .temporal import create_filter
from .run_folder import FrameKeys, RunFolder
from .sequences import Sequence, open_sequence

__all__ = ["SAMPLE_DIR", "main", "stage_stats", "check_same_frames", "calibrate_sequence", "default_out", "frame_keys",
           "with_camera"]

log = logging.getLogger(__name__)

SAMPLE_DIR = Path(__file__).with_name("sample")  #: the small real KITTI sample shipped in the package
_FINGERPRINT_CHECKS = 16  #: on resume, this many stored frames (spread out, the last included) are re-hashed


def stage_stats(timings: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Median and p90 milliseconds by stage over frames that ran the full pipeline."""
    full = [t for t in timings if "encode" in t]
    return {s: {"median": float(np.median([t[s] for t in full])), "p90": float(np.percentile([t[s] for t in full], 90))}
            for s in STAGES if full and all(s in t for t in full)}


PREFETCH = 2  #: frames after the current one whose local features are extracted ahead (``prefetch_features``)
Ahead = tuple[np.ndarray | ImageError, str, np.ndarray | None]  #: (image or why not, fingerprint, raw code or None)


def _read_and_encode(seq: Sequence, ids: list[int], descriptor: GlobalDescriptor | None) -> list[Ahead]:
    """Reads and decodes frames ``ids`` of ``seq``, then encodes the readable ones in one batch (codes None without
    a descriptor that encodes images alone, or when the batch fails: ``LoopDetector.process`` then encodes and
    reports)."""
    frames = [seq.read_frame(i) for i in ids]
    codes: list[np.ndarray | None] = [None] * len(frames)
    ok = [i for i, (image, _) in enumerate(frames) if not isinstance(image, ImageError)]
    if descriptor is not None and ok:
        try:
            batch = descriptor.encode_batch([frames[i][0] for i in ok])
        except ImageError:
            batch = [None] * len(ok)
        for i, code in zip(ok, batch):
            codes[i] = code
    return [(image, print_, code) for (image, print_), code in zip(frames, codes)]


def _ahead(seq: Sequence, ids: list[int], descriptor: GlobalDescriptor | None = None,
           batch: int = 8) -> Iterator[Ahead]:
    """Reads, decodes and encodes frames ``ids`` of ``seq`` (batches of ``batch``) in a worker thread, one batch
    ahead of the frame being processed: with single-threaded libraries (``cae_lcd.core.threads``) the worker and the caller
    each hold a core.

    Yields:
        ``(image or the reason it cannot be read, fingerprint, raw code or None)`` per id, in order.
    """
    chunks = [ids[i:i + batch] for i in range(0, len(ids), batch)]
    with ThreadPoolExecutor(1, thread_name_prefix="read-encode") as pool:
        pending = pool.submit(_read_and_encode, seq, chunks[0], descriptor) if chunks else None
        for nxt in [*chunks[1:], None]:
            current = pending.result()
            pending = pool.submit(_read_and_encode, seq, nxt, descriptor) if nxt is not None else None
            yield from current


def _looking_ahead(items: Iterator[Ahead], n: int) -> Iterator[tuple[Ahead, list[Ahead]]]:
    """Each item with the (up to) ``n`` items after it."""
    window: deque[Ahead] = deque()
    for item in items:
        window.append(item)
        if len(window) > n:
            current = window.popleft()
            yield current, list(window)
    while window:
        current = window.popleft()
        yield current, list(window)


def _frame_again(seq: Sequence, frame_id: int) -> np.ndarray:
    """Frame ``frame_id`` of ``seq`` read again (``LoopDetector``'s ``frame_source``: features needed late)."""
    image, _ = seq.read_frame(frame_id)
    if isinstance(image, ImageError):  # it was read when processed: changed or removed since
        raise ImageError(f"{seq.frame_name(frame_id)} can no longer be read ({image}); it was read when processed")
    return image


def check_same_frames(db: KeyframeDatabase, seq: Sequence) -> None:
    """Refuses to resume into a database made from other images.

    Every stored frame must have the same file name at the same index of ``seq``; a spread-out subset of them
    (``_FINGERPRINT_CHECKS``, the last one included) must also have the same size and content hash.

    Raises:
        ConfigError: names the first frame that differs and what it was.
    """
    entries = db.frames()
    if not entries:
        return
    where = f"{db.path} was built from other images than {seq.root}"
    for e in entries:
        if e.frame_id >= len(seq):
            raise ConfigError(f"{where}: it holds frame {e.frame_id} ({e.source}) but the folder has only "
                              f"{len(seq)} images; choose another --out")
        if e.source != seq.frame_name(e.frame_id):
            raise ConfigError(f"{where}: frame {e.frame_id} was {e.source}, now it is "
                              f"{seq.frame_name(e.frame_id)} (a file added or removed?); choose another --out")
    picks = np.unique(np.linspace(0, len(entries) - 1, min(len(entries), _FINGERPRINT_CHECKS)).round().astype(int))
    for e in (entries[i] for i in picks):
        if e.fingerprint and (seq.read_frame(e.frame_id)[1] or "unreadable") != e.fingerprint:
            raise ConfigError(f"{where}: frame {e.frame_id} ({e.source}) has changed since it was processed; "
                              "choose another --out")


def calibrate_sequence(seq: Sequence, conf: dict[str, Any], descriptor: GlobalDescriptor | None = None,
                       progress: bool = True, codes: dict[int, np.ndarray] | None = None,
                       features: dict[int, Any] | None = None) -> Calibration:
    """Calibrates on ``seq`` (unreadable frames are left out; ``detect`` warns about them).

    Args:
        codes: a dict that receives the raw codes of the frames read (encoded ahead, in batches, in a worker
            thread), for the run to reuse.
        features: a dict that receives the local features the calibration extracted, for the run to reuse.
    """
    conf = resolve_conf(conf)
    descriptor = descriptor if descriptor is not None else create_descriptor(conf["descriptor"])
    picks = calibration_frames(len(seq), conf["search"]["exclude_recent"], conf["temporal"].get("length", 1),
                               conf["calibration"]["max_frames"])
    codes = {} if codes is None else codes

    def frames() -> Iterator[tuple[int, np.ndarray]]:
        ids = [int(i) for i in picks]
        for i, (image, _, code) in zip(ids, _ahead(seq, ids, _batch_encoder(descriptor))):
            if not isinstance(image, ImageError):
                if code is not None:
                    codes[i] = code
                yield i, image

    return calibrate(Counted(frames(), len(picks)), len(seq), conf, descriptor, create_filter(conf["temporal"]), seq.K, progress,
                     codes, features)


def _batch_encoder(descriptor: GlobalDescriptor) -> GlobalDescriptor | None:
    """The descriptor when it can encode ahead in batches (same codes as one at a time), else None."""
    return descriptor if descriptor.encodes_in_batches and not descriptor.needs_features else None


def _calibration(run: RunFolder, seq: Sequence, conf: dict[str, Any], descriptor: GlobalDescriptor,
                 progress: bool, codes: dict[int, np.ndarray], features: dict[int, Any]) -> Calibration | None:
    """The run's look-ahead calibration: the one saved in the run folder, else a new one (saved; its codes and
    features go into ``codes`` and ``features``); None when disabled, or online (the stream calibrates itself)."""
    if not conf["calibration"]["enabled"] or conf["calibration"]["online"]:
        return None
    if run.calibration.is_file():
        cal = Calibration.load(run.calibration)
        if cal.descriptor != descriptor.identity:
            raise ConfigError(f"{run.calibration} was made with other weights ({cal.descriptor or 'unknown'}, now "
                              f"{descriptor.identity}); choose another --out or move it away to calibrate again")
        log.info("using the calibration in %s", run.calibration)
        return cal
    try:
        cal = calibrate_sequence(seq, conf, descriptor, progress, codes, features)
    except TooFewFrames as err:
        log.warning("not calibrated (%s): using the fixed policy (policy.min_inliers %d) and raw codes",
                    err, conf["policy"]["min_inliers"])
        return None
    cal.save(run.calibration)
    return cal


def _calibrated_detector(run: RunFolder, seq: Sequence, conf: dict[str, Any], progress: bool,
                         codes: dict[int, np.ndarray]) -> tuple[Calibration | None, LoopDetector]:
    """The run's calibration (``_calibration``; its codes go into ``codes``) and the detector that uses it, its
    local features and the sequence's files (to read a frame again when its features are needed late)."""
    descriptor = create_descriptor(conf["descriptor"])
    features: dict[int, Any] = {}
    cal = _calibration(run, seq, conf, descriptor, progress, codes, features)
    return cal, LoopDetector(conf, K=seq.K, database=run.database, calibration=cal, descriptor=descriptor,
                             frame_source=functools.partial(_frame_again, seq), features=features,
                             kept_geometries=KEPT_GEOMETRIES)


def default_out(seq: Sequence) -> Path:
    """The run folder when none is given: ``runs/<sequence name>`` (``runs/sample`` for the bundled sample)."""
    return Path("runs") / ("sample" if seq.root.resolve() == SAMPLE_DIR.resolve() else seq.name)


def _run_frames(det: LoopDetector, seq: Sequence, start: int, progress: bool,
                codes: dict[int, np.ndarray] | None = None) -> list[dict[str, float]]:
    """Processes frames ``start..`` of ``seq`` (``codes``: raw codes already computed, popped as they are used;
    the others are encoded ahead in a worker thread; the loops' poses refined as they are found, for their edges:
    ``retrieval.edges.PosesAhead``); returns the stage timings of the frames that ran."""
    with PosesAhead(det.verified_geometry) as poses:
        return _frames_through(det, seq, start, progress, {} if codes is None else codes, poses)


def _frames_through(det: LoopDetector, seq: Sequence, start: int, progress: bool, codes: dict[int, np.ndarray],
                    poses: PosesAhead) -> list[dict[str, float]]:
    """``_run_frames``' loop over the frames."""
    timings: list[dict[str, float]] = []
    bar = progress_bar(range(start, len(seq)), desc=f"detect {seq.name}", unit="frame", disable=not progress,
                       initial=start, total=len(seq))
    n_loops = 0
    todo = list(range(start, len(seq)))
    encoder = _batch_encoder(det.descriptor) if len(codes) < len(todo) else None
    for i, ((image, print_, code), upcoming) in zip(bar, _looking_ahead(_ahead(seq, todo, encoder), PREFETCH)):
        for k, (later, _, _) in enumerate(upcoming, start=i + 1):
            if not isinstance(later, ImageError):
                try:
                    det.prefetch_features(later, k)  # extracted beside this frame's verification
                except ImageError:  # reported when that frame is processed
                    pass
        name = seq.frame_name(i)
        code = codes.pop(i, code)
        if not isinstance(image, ImageError):
            try:
                res = det.process(image, i, None if seq.timestamps is None else float(seq.timestamps[i]),
                                  None if seq.poses is None else seq.poses[i], name, print_, code)
            except ImageError as err:
                image = err
            else:
                timings.append(res.ms)
                poses.add([*([(i, res.loop.frame_id)] if res.loop is not None else []),
                           *((q, c.frame_id) for q, c in res.confirmed)])
                n_loops += (res.loop is not None) + len(res.confirmed)  # delayed loops too (each reported once)
                bar.set_postfix(loops=n_loops, ms=f"{res.ms['total']:.0f}")
                continue
        log.warning("skipping frame %d: %s", i, image)
        det.record_unreadable(i, name, print_, str(image))
    return timings


def with_camera(seq: Sequence, conf: dict[str, Any] | None, given: CameraModel | None) -> dict[str, Any]:
    """The camera a run uses: ``given`` (``--intrinsics`` / ``--camera-info``), else the sequence's own with its
    distortion (EuRoC ``sensor.yaml``, a bag's ``CameraInfo``); its ``K`` becomes ``seq.K`` and its distortion the
    conf's ``geometry.distortion_*`` (returned: ``conf`` with them, unchanged without a camera model)."""
    cam = given if given is not None else seq.camera
    conf = dict(conf or {})
    if cam is None:
        return conf
    seq.K, seq.camera = cam.K, cam
    geometry = conf.get("geometry") or {}
    if not isinstance(geometry, dict):
        raise ConfigError("config section 'geometry' must be a mapping")
    conf["geometry"] = {**geometry, **cam.geometry_conf()}
    if cam.model != "none":
        log.info("camera %s: %s distortion %s; keypoints undistorted before the geometric check", cam.source,
                 cam.model, list(cam.coefficients))
    return conf


def _edges(seq: Sequence, resolved: dict[str, Any], cal: Calibration | None, det: LoopDetector,
           loops: np.ndarray) -> list[Any]:
    """The loops' edges (``retrieval.edges.loop_edges``; only where the loops were verified), from the run's own
    checks (``LoopDetector.verified_geometry``) or its own local features on every core; for a calibrated run whose
    features are cheaper than the extractor's (``calibration.features_px``), the edges they give least surely made
    again at the extractor's own resolution, read again from the frames (``retrieval.edges.edge_features``: 2
    extractions a loop, for those only)."""
    features = serialised(det.keyframe_features)
    precise = None
    if cal is not None and calibrated_features(resolved) != resolved["features"]:
        precise = edge_features(lambda i: seq.read_frame(i)[0], resolved["features"], features)
    return loop_edges(features, loops, seq.K, resolved, workers=cpu_count(), precise=precise,
                      verified=det.verified_geometry)


def _body_pose(seq: Sequence, edge_frame: str) -> np.ndarray | None:
    """The camera's pose on the body ``(4, 4)`` when the edges are asked for in the body's frame, else None.

    Raises:
        ConfigError: ``"body"`` for a camera whose pose on the body is not known.
    """
    if edge_frame != "body":
        return None
    T = None if seq.camera is None else seq.camera.T_body_camera
    if T is None:
        raise ConfigError(f"--edge-frame body: the camera's pose on the body is not known for {seq.root} (EuRoC's "
                          "sensor.yaml T_BS, or --camera-info with T_BS or a Kalibr camchain's T_cam_imu)")
    return T


def frame_keys(seq: Sequence) -> FrameKeys:
    """Each frame's timestamp and id in its source (``Sequence.source_id``), for the run folder's tables."""
    return FrameKeys(seq.timestamps, [seq.source_id(i) for i in range(len(seq))])


def _with_confirmed(query: int, cands: np.ndarray, loop: int, confirmed: tuple[int, float] | None,
                    scores: Callable[[int, int], tuple[float, float]]) -> tuple[int, np.ndarray, int]:
    """A stored row ``(query, candidates (k, 6), loop)`` with its delayed loop, if any
    (``LoopDetector.confirmed_loops``: the keyframe and the accepting run's confidence, written as the candidate's, as
    the API reports it); a keyframe that was not among the frame's stored hypotheses (a stop's carry, found at a
    refit) is added as a candidate row, ``scores(query, keyframe)`` giving its ``(score, seq_score)``, unverified."""
    if confirmed is None or loop >= 0:
        return query, cands, loop
    cands = cands.copy()
    hit = cands[:, 0] == confirmed[0]
    if hit.any():
        cands[hit, 5] = confirmed[1]
    else:
        score, seq_score = scores(query, confirmed[0])
        cands = np.vstack([cands.reshape(-1, 6), [confirmed[0], score, 0, -1, seq_score, confirmed[1]]])
    return query, cands, confirmed[0]


def _log_seconds(seconds: dict[str, float]) -> None:
    """One line: the wall time of the calibration (its own work apart from the run's work it did ahead) and of the
    frames."""
    if "calibration_online" in seconds:
        log.info("seconds: frames %.1f, of which the stream's own calibration (records, checks, refits) %.1f",
                 seconds["frames"], seconds["calibration_online"])
        return
    if "calibration_own" not in seconds:
        log.info("seconds: calibration %.1f, frames %.1f", seconds["calibration"], seconds["frames"])
        return
    wall = seconds["calibration"] + seconds["frames"]
    log.info("seconds: calibration %.1f (its own work %.1f = %.0f %% of the run's %.1f s; reading, encoding and "
             "local features the run reuses %.1f), frames %.1f", seconds["calibration"], seconds["calibration_own"],
             100 * seconds["calibration_own"] / max(wall, 1e-9), wall, seconds["calibration_shared"],
             seconds["frames"])


def _summary(seq: Sequence, run: RunFolder, resolved: dict[str, Any], cal: Calibration | None, frames: list[Any], *,
             stride: int, processed: int, start: int, keyframes: int, loops: int, confirmed: int, edges: list[Any],
             edge_frame: str, timings: list[dict[str, float]], seconds: dict[str, float]) -> dict[str, Any]:
    """The run's ``summary.json`` (``main``'s return): the sequence, what this run processed, the loops and edges,
    the stage timings and the calibration's notes (``frames``: the store's frame entries; the ground truth's poses
    written into the run folder where the sequence's poses are its ground truth)."""
    unreadable = [e.source for e in frames if e.kind == "unreadable"]
    truth = seq.ground_truth
    if truth is None and seq.poses_are_truth and seq.poses is not None:
        truth = run.write_ground_truth_poses(seq.poses)
    return {
        "sequence": str(seq.root.resolve()), "frames": len(seq), "stride": stride, "processed_this_run": processed,
        "resumed_at": start, "keyframes": keyframes, "gated_out": sum(e.kind == "gated" for e in frames),
        "unreadable": len(unreadable), "unreadable_files": unreadable, "loops": loops, "confirmed": confirmed,
        "loop_edges": len(edges), "metric_edges": sum(e.metric for e in edges), "edge_frame": edge_frame,
        "ms_per_frame": stage_stats(timings), "seconds": seconds, "out": str(run.root),
        "ground_truth_file": None if truth is None else str(truth),
        "camera": None if seq.camera is None else {"source": seq.camera.source, "K": seq.camera.K.tolist(),
                                                   "distortion_model": seq.camera.model,
                                                   "distortion_coefficients": list(seq.camera.coefficients),
                                                   "T_body_camera": None if seq.camera.T_body_camera is None
                                                   else seq.camera.T_body_camera.tolist()},
        "calibration": None if cal is None else {"notes": cal.notes, "accept_at_confidence": cal.accept_at,
                                                 "thresholds": cal.thresholds(),
                                                 "verification": bool(cal.inlier_null),
                                                 "online": bool(resolved["calibration"]["online"])},
    }


def main(path: str | Path | Sequence | None = None, out: str | Path | None = None,
         conf: dict[str, Any] | None = None, camera: str | None = None, progress: bool = True,
         topic: str | None = None, stride: int = 1, intrinsics: str | None = None,
         camera_info: str | Path | None = None, metric_from_poses: bool = False,
         edge_frame: str = "camera") -> dict[str, Any]:
    """Runs loop-closure detection over a sequence and writes the run folder.

    Args:
        path: a sequence of any layout ``retrieval.sequences.open_sequence`` reads (KITTI, TUM, EuRoC or image
            folder, bag, video), or one already opened (a ``Sequence``: ``camera``, ``topic`` and ``stride`` are
            then its own; opened once, its readers' warnings are said once); None = the bundled sample.
        out: run folder; None = ``runs/<sequence name>`` (``runs/sample`` for the sample). An existing run there
            is resumed (same conf, weights and images required).
        conf: overrides of the detector's ``default_conf``.
        camera: KITTI camera folder (``image_0``, ``image_2``); None = the first present.
        progress: show a progress bar.
        topic: a bag's image topic; None = the bag's only one.
        stride: a video's frames taken: every ``stride``-th.
        intrinsics: ``"fx,fy,cx,cy"``: the camera's ``K`` (over the sequence's own, and a ``camera_info``'s).
        camera_info: a camera file (``verify.camera.read_camera_file``: ROS ``camera_info``, Kalibr camchain,
            EuRoC ``sensor.yaml`` or ``intrinsics`` + ``distortion_model`` + ``distortion_coefficients``); its
            distortion undistorts the keypoints before the geometric check. None: the sequence's own camera.
        metric_from_poses: loop edges at the length between the two frames' positions in the sequence's poses
            (``retrieval.edges.metric_edges``: poses you trust for the baseline, e.g. your odometry as a TUM
            ``groundtruth.txt``); False: up to scale.
        edge_frame: the frame the loop edges and their vertices are written in (``retrieval.edges.EDGE_FRAMES``):
            ``"camera"``, or ``"body"``: the body the camera is mounted on, through the camera's pose on it (EuRoC's
            ``sensor.yaml`` ``T_BS``, a camera file's ``T_BS`` or Kalibr ``T_cam_imu``; ``retrieval.edges.body_edges``).

    Returns:
        The summary dict also written to ``summary.json``.

    Raises:
        ConfigError: a bad path, conf value or metadata file, or a run folder made from other data; raised before
            anything is written.
        DatabaseError: the database is damaged, locked or cannot be written; files already written stay as they were.
    """
    check_edge_frame(edge_frame)
    given = camera_from_options(intrinsics, camera_info)
    if isinstance(path, Sequence):  # opened by the caller: its stride is the one it was opened with
        seq, stride = path, getattr(path.stream, "stride", 1)
    else:
        seq = open_sequence(SAMPLE_DIR if path is None else path, camera, topic, stride)
    conf = with_camera(seq, conf, given)
    T_body_camera = _body_pose(seq, edge_frame)
    resolved = resolve_conf(conf)
    apply_thread_policy(resolved["runtime"]["threads"])  # before the calibration: its whitening uses BLAS too
    out = Path(out) if out is not None else default_out(seq)
    created = not out.exists()
    run = RunFolder(prepare_out_dir(out))
    run.check_resumable()  # results without a database: nothing to resume, and they would be overwritten
    codes: dict[int, np.ndarray] = {}  # the calibration's codes, reused by the run
    try:
        t0 = time.perf_counter()
        cal, det = _calibrated_detector(run, seq, resolved, progress, codes)
        seconds = {"calibration": time.perf_counter() - t0}
    except BaseException:
        if created:  # e.g. weights that cannot be loaded: leave no trace
            run.calibration.unlink(missing_ok=True)
            if not any(run.root.iterdir()):
                run.root.rmdir()
        raise
    with det:
        check_same_frames(det.db, seq)
        dump_conf(resolved, run.conf)  # only once the database accepted this conf: nothing is overwritten
        start = det.next_frame_id
        if start >= len(seq):
            log.info("%s already holds all %d frames; rewriting the tables", run.database, len(seq))
        elif start:
            log.info("resuming at frame %d of %d", start, len(seq))
        t0 = time.perf_counter()
        timings = _run_frames(det, seq, start, progress, codes)
        seconds["frames"] = time.perf_counter() - t0
        if any("calibrate" in t for t in timings):  # online: records, checks, refits, inside the frames' time
            seconds["calibration_online"] = sum(t.get("calibrate", 0.0) for t in timings) / 1e3
        seconds.update({f"calibration_{k}": v for k, v in (cal.seconds if cal is not None else {}).items()})
        _log_seconds(seconds)
        cal = det.calibration  # the look-ahead one, or the stream's own at its end (online)
        keys = frame_keys(seq)
        rows = list(det.db.results())
        confirmed = det.confirmed_loops(rows)  # delayed loops: a run accepted at t certifies its earlier frames
        loops = run.write_tables((_with_confirmed(q, cands, loop, confirmed.get(q), det.pair_scores)
                                   for q, cands, loop in rows), keys)
        verified = bool(cal.inlier_null) if cal is not None else bool(resolved["policy"]["verify"])
        t0 = time.perf_counter()
        edges = _edges(seq, resolved, cal, det, loops) if verified else []
        seconds["loop_edges"] = time.perf_counter() - t0
        log.info("loop edges: %d of %d loops in %.1f s", len(edges), len(loops), seconds["loop_edges"])
        if metric_from_poses:
            edges = metric_edges(edges, seq.poses)
        run.write_edges(edges, seq.poses, keys, T_body_camera)
        frames = det.db.frames()
        keyframes = len(det.db)
    summary = _summary(seq, run, resolved, cal, frames, stride=stride, processed=len(timings), start=start,
                       keyframes=keyframes, loops=len(loops), confirmed=len(confirmed), edges=edges,
                       edge_frame=edge_frame, timings=timings, seconds=seconds)
    run.write_summary(summary)
    return summary
