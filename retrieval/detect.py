"""Offline detection over a sequence: ``cae-lcd detect [PATH]`` (the same path as ``LoopDetector.process``).

Writes into the run folder:

- ``conf.yaml``: the resolved configuration;
- ``keyframes.h5``: the keyframe database (a killed run resumes from it);
- ``loops.csv``: ``query,match,score,matches,inliers``, one row per accepted loop (best match per query);
- ``candidates.csv``: every verified candidate ``query,candidate,score,matches,inliers,accepted`` (for PR curves);
- ``summary.json``: counts, ms/frame by stage, and precision/recall when the sequence has ground truth.
"""

from __future__ import annotations

import csv
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from tqdm import tqdm

from cae.conf import ConfigError, dump_conf, load_conf_file
from cae.preprocess import ImageError, read_image
from evaluation.metrics import precision_recall

from .database import KeyframeDatabase
from .detector import LoopDetector, resolve_conf
from .sequences import Sequence, open_sequence

__all__ = ["SAMPLE_DIR", "main", "write_tables", "stage_stats"]

log = logging.getLogger(__name__)

SAMPLE_DIR = Path(__file__).with_name("sample")  #: the small real KITTI sample shipped in the package
STAGES = ("gate", "encode", "features", "search", "verify", "insert", "total")


def write_tables(db: KeyframeDatabase, out: Path) -> np.ndarray:
    """Writes ``loops.csv`` and ``candidates.csv`` from the database; returns the loops ``(L, 2)``."""
    loops = []
    with open(out / "loops.csv", "w", newline="") as f_loops, open(out / "candidates.csv", "w", newline="") as f_c:
        wl, wc = csv.writer(f_loops), csv.writer(f_c)
        wl.writerow(["query", "match", "score", "matches", "inliers"])
        wc.writerow(["query", "candidate", "score", "matches", "inliers", "accepted"])
        for q, candidates, loop in db.results():
            for cid, score, matches, inliers in candidates:
                row = [q, int(cid), f"{score:.6f}", int(matches), int(inliers)]
                wc.writerow(row + [int(int(cid) == loop)])
                if int(cid) == loop:
                    wl.writerow(row)
                    loops.append((q, loop))
    return np.array(loops, np.int64).reshape(-1, 2)


def stage_stats(timings: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Median and p90 milliseconds by stage over frames that ran the full pipeline."""
    full = [t for t in timings if "encode" in t]
    return {s: {"median": float(np.median([t[s] for t in full])), "p90": float(np.percentile([t[s] for t in full], 90))}
            for s in STAGES if full and all(s in t for t in full)}


def _read_or_error(path: Path) -> np.ndarray | ImageError:
    try:
        return read_image(path)
    except ImageError as err:
        return err


def _prefetch(paths: list[Path]) -> Iterator[np.ndarray | ImageError]:
    """Decodes the next image in a worker thread while the current one is processed (one frame ahead)."""
    with ThreadPoolExecutor(1, thread_name_prefix="read") as pool:
        pending = pool.submit(_read_or_error, paths[0]) if paths else None
        for nxt in [*paths[1:], None]:
            current = pending.result()
            pending = pool.submit(_read_or_error, nxt) if nxt is not None else None
            yield current


def _default_out(seq: Sequence) -> Path:
    return Path("runs") / ("sample" if seq.root.resolve() == SAMPLE_DIR.resolve() else seq.root.name)


def main(path: str | Path | None = None, out: str | Path | None = None, conf: dict[str, Any] | None = None,
         camera: str | None = None, progress: bool = True) -> dict[str, Any]:
    """Runs loop-closure detection over a sequence and writes the run folder.

    Args:
        path: KITTI sequence folder or folder of images; None = the bundled sample.
        out: run folder; None = ``runs/<sequence name>`` (``runs/sample`` for the sample). An existing run there
            is resumed (same conf and weights required).
        conf: overrides of the detector's ``default_conf``.
        camera: KITTI camera folder (``image_0``, ``image_2``); None = the first present.
        progress: show a progress bar.

    Returns:
        The summary dict also written to ``summary.json``.
    """
    seq = open_sequence(SAMPLE_DIR if path is None else path, camera)
    out = Path(out) if out is not None else _default_out(seq)
    out.mkdir(parents=True, exist_ok=True)
    resolved = resolve_conf(conf)
    unreadable: list[str] = []
    timings: list[dict[str, float]] = []
    with LoopDetector(resolved, K=seq.K, database=out / "keyframes.h5") as det:
        dump_conf(resolved, out / "conf.yaml")  # only once the database accepted this conf: nothing is overwritten
        start = det.next_frame_id
        if start >= len(seq):
            log.info("%s already holds all %d frames; rewriting the tables", out / "keyframes.h5", len(seq))
        elif start:
            log.info("resuming at frame %d of %d", start, len(seq))
        bar = tqdm(range(start, len(seq)), desc=f"detect {seq.root.name}", unit="frame", disable=not progress,
                   initial=start, total=len(seq))
        n_loops = 0
        for i, image in zip(bar, _prefetch(seq.frames[start:])):
            if isinstance(image, ImageError):
                log.warning("skipping frame %d: %s", i, image)
                unreadable.append(seq.frames[i].name)
                continue
            res = det.process(image, i, None if seq.timestamps is None else float(seq.timestamps[i]),
                              None if seq.poses is None else seq.poses[i], seq.frames[i].name)
            timings.append(res.ms)
            n_loops += res.loop is not None
            bar.set_postfix(loops=n_loops, ms=f"{res.ms['total']:.0f}")
        loops = write_tables(det.db, out)
        gated = len(det.db.gated())
        keyframes = len(det.db)
    summary: dict[str, Any] = {
        "sequence": str(seq.root.resolve()), "frames": len(seq), "processed_this_run": len(timings), "resumed_at": start,
        "keyframes": keyframes, "gated_out": gated, "unreadable": len(unreadable), "unreadable_files": unreadable,
        "loops": len(loops), "ms_per_frame": stage_stats(timings), "out": str(out),
    }
    if seq.loops is not None:
        summary["ground_truth"] = precision_recall(loops, seq.loops).as_dict()
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def log_summary(s: dict[str, Any]) -> None:
    """The end-of-run report, one line per fact."""
    log.info("frames %d (this run %d), keyframes %d, gated out %d, unreadable %d, loops %d", s["frames"],
             s["processed_this_run"], s["keyframes"], s["gated_out"], s["unreadable"], s["loops"])
    if s["ms_per_frame"]:
        log.info("ms/frame (median): %s", ", ".join(f"{k} {v['median']:.1f}" for k, v in s["ms_per_frame"].items()))
    if "ground_truth" in s:
        g = s["ground_truth"]
        recall = "n/a" if g["recall"] is None else f"{g['recall']:.3f}"
        log.info("against ground truth: precision %.3f (%d/%d), recall %s (%d of %d queries with a true loop)",
                 g["precision"], g["true_positives"], g["detections"], recall, g["true_positives"], g["positives"])
    log.info("wrote %s/{loops.csv,candidates.csv,keyframes.h5,conf.yaml,summary.json}", s["out"])


def add_parser(sub: Any) -> None:
    p = sub.add_parser("detect", help="detect loop closures over a sequence (no PATH: the bundled sample)",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("path", nargs="?", help="KITTI sequence folder or image folder (default: bundled sample)")
    p.add_argument("--config", help="YAML config (default: the built-in defaults = configs/default.yaml)")
    p.add_argument("--out", help="run folder (default: runs/<sequence name>); an existing run is resumed")
    p.add_argument("--camera", choices=["image_0", "image_1", "image_2", "image_3"], help="KITTI camera folder")
    p.add_argument("--weights", help="encoder checkpoint (default: the shipped weights)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


def _run(args: Any) -> None:
    conf = load_conf_file(args.config) if args.config else {}
    if args.weights:
        conf.setdefault("encoder", {})
        if not isinstance(conf["encoder"], dict):
            raise ConfigError("config section 'encoder' must be a mapping")
        conf["encoder"]["weights"] = args.weights
    log_summary(main(args.path, args.out, conf, args.camera, progress=not args.no_progress))
