"""``cae-lcd detect [PATH]``: ``retrieval.detect.main``, then precision/recall when the sequence has ground truth."""

from __future__ import annotations

import logging
from functools import partial
from pathlib import Path
from typing import Any

from cae_lcd.core.cli import api_defaults
from cae_lcd.core.conf import ConfigError, load_conf_file
from cae_lcd.evaluation.scored import detect_and_score

from .evaluate import add_world_argument
from retrieval import detect
from retrieval.detector import default_conf
from retrieval.methods import METHODS, method_conf
from retrieval.batch import run_batch
from retrieval.edges import EDGE_FRAMES
from retrieval.sequences import find_sequences

__all__ = ["add_parser", "run", "log_summary", "log_table", "conf_from_args", "add_sequence_arguments"]

log = logging.getLogger("cae_lcd.detect")

_DEFAULTS = api_defaults(detect.main)
_BATCH = api_defaults(run_batch)
_SCORED = api_defaults(detect_and_score)


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
    cal = s.get("calibration")
    if cal is not None:
        log.info("calibrated%s: accept at confidence >= %.2f (%s); local verification %s",
                 " on the stream itself (at its end)" if cal.get("online") else " on a look-ahead pass",
                 cal["accept_at_confidence"],
                 ", ".join(f"{k} >= {v:.4g}" for k, v in cal["thresholds"].items() if v is not None)
                 or "no pair alone: a run of frames on one offset",
                 "on" if cal["verification"] else "off (too few local features)")
    written = "loops.csv,candidates.csv,keyframes.h5," + ("calibration.h5," if cal and not cal.get("online") else "") \
        + "loop_edges.g2o,loop_edges.csv,loop_edges.json,"
    log.info("wrote %s/{%sconf.yaml,summary.json}", s["out"], written)


def add_parser(sub: Any) -> None:
    p = sub.add_parser("detect", help="detect loop closures over a sequence, or many (on Ray with --workers; no PATH: the bundled sample)",
                       description=detect.__doc__.split("\n\n")[0])
    add_sequence_arguments(p)
    p.add_argument("--out", help="run folder (default: runs/<sequence name>); an existing run is resumed. PATH "
                   "holding many sequences (a folder of them, or a .txt list): one run folder a sequence in OUT")
    p.add_argument("--workers", type=int, default=_BATCH["workers"],
                   help="many sequences: sequences at once on a local Ray (default: no Ray, one after the other)")
    p.add_argument("--intrinsics", default=_DEFAULTS["intrinsics"], metavar="FX,FY,CX,CY",
                   help="the camera's intrinsics in pixels (over the sequence's own and --camera-info's): enables the "
                        "essential matrix and the loop edges for a folder, a video or TUM")
    p.add_argument("--camera-info", default=_DEFAULTS["camera_info"], metavar="FILE",
                   help="a camera file: ROS camera_info YAML, Kalibr camchain, EuRoC sensor.yaml, or 'intrinsics: [fx, "
                        "fy, cx, cy]' with distortion_model (radtan, equidistant) and distortion_coefficients; "
                        "keypoints are undistorted before the geometric check")
    add_world_argument(p, _SCORED["world"])
    p.add_argument("--metric-edges", action="store_true", default=_SCORED["metric_from_poses"],
                   help="loop edges at the distance between the two frames in the sequence's poses (poses you trust "
                        "for the baseline: your odometry); default: up to scale, the length unobserved")
    p.add_argument("--edge-frame", choices=list(EDGE_FRAMES), default=_SCORED["edge_frame"],
                   help="the frame of the loop edges and their vertices: the camera's, or the body's it is mounted on "
                        "(through EuRoC's sensor.yaml T_BS, or --camera-info with T_BS or a Kalibr T_cam_imu; "
                        "default %(default)s)")
    p.add_argument("--lookahead", action="store_true", default=not default_conf["calibration"]["online"],
                   help="calibrate on a look-ahead pass over the whole sequence first and decide with that calibration "
                        "fixed (calibration.online: false); default: the run calibrates itself as it streams, the same "
                        "algorithm as the Python API (retrieval.online)")
    p.add_argument("--ray-address", default=_BATCH["address"],
                   help="many sequences: a Ray cluster to run on (default: a local Ray with --workers, else no Ray)")
    p.set_defaults(func=run)


def add_sequence_arguments(p: Any) -> None:
    """PATH, --method, --config, --camera, --weights, --no-progress: what every command that reads a sequence
    takes."""
    p.add_argument("path", nargs="?", help="a sequence: KITTI, TUM, EuRoC or image folder, a ROS bag (.bag, .db3, "
                   ".mcap, ROS 2 bag folder) or a video (default: bundled sample)")
    p.add_argument("--method", choices=list(METHODS), default="cae",
                   help="detection method (default: cae; mild: MILD, Han & Fang 2017; mild+verify: MILD's "
                        "candidates + SIFT/geometric verification); --config merges on top")
    p.add_argument("--config", help="YAML config file, or a shipped preset by name: paper, mild, mild_verify, "
                   "default (default: the built-in defaults = the default preset)")
    p.add_argument("--camera", choices=["image_0", "image_1", "image_2", "image_3", "images"],
                   help="camera folder inside PATH")
    p.add_argument("--weights", help="encoder checkpoint (default: the shipped weights)")
    p.add_argument("--topic", default=_DEFAULTS["topic"], help="a bag's image topic (default: the bag's only one)")
    p.add_argument("--stride", type=int, default=_DEFAULTS["stride"],
                   help="a video: take every n-th frame (default %(default)s)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def conf_from_args(args: Any) -> dict[str, Any]:
    """The conf overrides from ``--method``, ``--config`` and ``--weights``."""
    conf = method_conf(args.method, load_conf_file(args.config) if args.config else {})
    if args.weights:
        conf.setdefault("descriptor", {})
        if not isinstance(conf["descriptor"], dict):
            raise ConfigError("config section 'descriptor' must be a mapping")
        conf["descriptor"]["weights"] = args.weights
    return conf


def log_table(rows: list[dict[str, Any]], out: Path) -> None:
    """The batch's summary table, one logged line a sequence."""
    log.info("%-28s %6s %6s %9s %7s %9s  %s", "sequence", "frames", "loops", "precision", "recall", "ms/frame",
             "status")
    for r in rows:
        cells = [("-" if r[k] is None else f"{r[k]:.3f}" if isinstance(r[k], float) else r[k])
                 for k in ("frames", "loops", "precision", "recall", "ms_per_frame")]
        log.info("%-28s %6s %6s %9s %7s %9s  %s", Path(r["sequence"]).name[:28], *cells, r["status"])
    log.info("wrote %s/{summary.csv,summary.json} and one run folder a sequence", out)


def run(args: Any) -> None:
    conf = conf_from_args(args)
    if args.lookahead:
        section = conf.setdefault("calibration", {})
        if not isinstance(section, dict):
            raise ConfigError("config section 'calibration' must be a mapping")
        section["online"] = False
    many = None if args.path is None else find_sequences(args.path)
    if many is None:
        log_summary(detect_and_score(args.path, args.out, conf, args.camera, not args.no_progress, args.topic,
                                     args.stride, args.intrinsics, args.camera_info, args.world,
                                     args.metric_edges, args.edge_frame))
        return
    if args.out is None:
        raise ConfigError(f"{args.path} holds {len(many)} sequences: pass --out DIR (one run folder a sequence)")
    task = partial(detect_and_score, conf=conf, camera=args.camera, progress=False, topic=args.topic,
                   stride=args.stride, intrinsics=args.intrinsics, camera_info=args.camera_info, world=args.world,
                   metric_from_poses=args.metric_edges, edge_frame=args.edge_frame)
    rows = run_batch(many, args.out, task, args.workers, args.ray_address, not args.no_progress)
    log_table(rows, Path(args.out))
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        raise ConfigError(f"{len(failed)} of {len(rows)} sequences failed (first: {failed[0]['sequence']}: "
                          f"{failed[0]['status']}); the others' results are written")
