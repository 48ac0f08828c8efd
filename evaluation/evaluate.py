"""Evaluate a detect run against ground truth: ``cae-lcd evaluate RUN_DIR_OR_LOOPS_CSV --gt GROUND_TRUTH``.

Reports precision/recall per query at the operating point, the PR curve swept over the verification score (max
recall at 100 % precision, AUC as average precision), and Recall@1/5/10 of the retrieval stage alone. Writes
``evaluation.json`` (``format_version`` 1) and ``pr_curve.png``, ``trajectory.png``, ``similarity.png``.
"""

from __future__ import annotations

import csv
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cae.cli import api_defaults
from cae.conf import ConfigError
from retrieval.database import KeyframeDatabase
from retrieval.sequences import read_kitti_poses

from .ground_truth import GroundTruth, load_ground_truth, sniff_ground_truth
from .metrics import SCORES, best_per_query, correct_mask, pr_curve, precision_recall, recall_at_k

__all__ = ["FORMAT_VERSION", "KS", "main", "read_csv_table", "add_parser"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
KS = (1, 5, 10)  #: Recall@k cut-offs
LOOPS_COLUMNS = ("query", "match", "score", "matches", "inliers")
CANDIDATE_COLUMNS = ("query", "candidate", "score", "matches", "inliers", "accepted")


def read_csv_table(path: Path, columns: tuple[str, ...]) -> np.ndarray:
    """A numeric CSV with a header holding at least ``columns`` -> ``(R, len(columns))`` float64 in that order.

    Raises:
        ConfigError: missing file, missing column or a non-numeric cell (the message names the file and line).
    """
    if not path.is_file():
        raise ConfigError(f"not found: {path}")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        missing = [c for c in columns if c not in (reader.fieldnames or [])]
        if missing:
            raise ConfigError(f"{path}: missing column(s) {', '.join(missing)}; expected {','.join(columns)}")
        try:
            rows = [[float(r[c]) for c in columns] for r in reader]
        except (TypeError, ValueError):
            raise ConfigError(f"{path}: non-numeric value on line {reader.line_num}") from None
    return np.array(rows, np.float64).reshape(-1, len(columns))


def _read_yaml(path: Path) -> dict[str, Any]:
    try:
        data = yaml.safe_load(path.read_text()) if path.is_file() else None
    except (OSError, yaml.YAMLError):
        log.warning("cannot read %s; using no run conf", path)
        return {}
    return data if isinstance(data, dict) else {}


def _read_summary(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        log.warning("cannot read %s; evaluating without it", path)
        return {}
    return data if isinstance(data, dict) else {}


def _sequence_file(summary: dict[str, Any], *names: str) -> Path | None:
    """A file beside the run's sequence (``summary.json`` "sequence"), e.g. ``times.txt``, or None."""
    if "sequence" not in summary:
        return None
    root = Path(summary["sequence"])
    cands = {"times": [root / "times.txt"],
             "poses": [root / "poses.txt", root.parent.parent / "poses" / f"{root.name}.txt"]}
    return next((p for n in names for p in cands[n] if p.is_file()), None)


def _keyframes(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Codes ``(n, D)``, frame ids ``(n,)`` and poses ``(n, 3, 4)`` (NaN when unknown) from ``keyframes.h5``."""
    with KeyframeDatabase(path, mode="r") as db:
        codes, ids = db.codes()
        poses = db.poses()
    return (codes.astype(np.float32) if len(codes) else np.zeros((0, 1), np.float32)), ids, poses


def _resolve_run(run: Path) -> tuple[Path, Path]:
    run = Path(run)
    if run.is_dir():
        if not (run / "loops.csv").is_file():
            raise ConfigError(f"{run} holds no loops.csv; pass a run folder written by 'cae-lcd detect' or a loops.csv")
        return run, run / "loops.csv"
    if run.is_file():
        return run.parent, run
    raise ConfigError(f"run not found: {run}")


def main(run: Path, gt: Path, out: Path | None = None, radius: float = 5.0, min_gap: int = 50,
         min_gap_s: float | None = None, score: str = "inliers", times: Path | None = None) -> dict[str, Any]:
    """Evaluates a detect run against ground truth and writes the report and plots.

    Args:
        run: run folder written by ``cae-lcd detect``, or a ``loops.csv`` file (then only the operating point is
            computed unless ``candidates.csv`` / ``keyframes.h5`` lie beside it).
        gt: pairs file (``i j`` a line, 0-based) or KITTI poses file (12 numbers a line; row = frame id).
        out: folder for ``evaluation.json`` and the PNGs; None = the run folder.
        radius: metres, for pose-derived ground truth.
        min_gap: minimum frame gap, for pose-derived ground truth.
        min_gap_s: minimum time gap (seconds) instead of ``min_gap``; needs timestamps (``times`` or the run's
            sequence ``times.txt``).
        score: the score the PR curve sweeps: ``"inliers"`` or ``"cosine"``.
        times: ``times.txt`` (one timestamp a frame) for ``min_gap_s``; None = the run's sequence's.

    Returns:
        The report written to ``evaluation.json``.

    Raises:
        ConfigError: unreadable run or ground truth, or poses that do not match the run's frames.
    """
    if score not in SCORES:
        raise ConfigError(f"unknown score '{score}'; choose one of {', '.join(SCORES)}")
    if radius <= 0 or min_gap < 0 or (min_gap_s is not None and min_gap_s < 0):
        raise ConfigError("radius must be > 0 and the minimum gaps >= 0")
    from .plots import plot_pr_curve, plot_similarity, plot_trajectory  # matplotlib only when evaluating

    run_dir, loops_csv = _resolve_run(run)
    out = Path(out) if out is not None else run_dir
    out.mkdir(parents=True, exist_ok=True)
    summary_path, cand_path, kf_path = run_dir / "summary.json", run_dir / "candidates.csv", run_dir / "keyframes.h5"
    summary = _read_summary(summary_path)
    run_conf = _read_yaml(run_dir / "conf.yaml")
    policy = run_conf.get("policy") or {}

    timestamps = None
    if min_gap_s is not None and sniff_ground_truth(gt) == "poses":
        tpath = Path(times) if times is not None else _sequence_file(summary, "times")
        if tpath is None:
            raise ConfigError("--min-gap-s needs timestamps: pass --times, or run on a sequence with times.txt")
        try:
            timestamps = np.loadtxt(tpath, ndmin=1)
        except (OSError, ValueError) as err:
            raise ConfigError(f"cannot read timestamps {tpath}: {err}") from None
    truth: GroundTruth = load_ground_truth(gt, radius, min_gap, timestamps, min_gap_s)

    loops = read_csv_table(loops_csv, LOOPS_COLUMNS)
    cands = read_csv_table(cand_path, CANDIDATE_COLUMNS) if cand_path.is_file() else None
    ids_seen = np.concatenate([loops[:, :2].ravel(), [] if cands is None else cands[:, :2].ravel()]).astype(np.int64)
    n_frames = int(summary.get("frames", 0)) or int(max(ids_seen.max(initial=-1), truth.pairs.max(initial=-1)) + 1)
    if truth.kind == "poses" and ("frames" in summary and len(truth.poses) != n_frames
                                  or ids_seen.max(initial=-1) >= len(truth.poses)):
        raise ConfigError(f"{truth.path} has {len(truth.poses)} poses but the run has {n_frames} frames "
                          f"(frame ids up to {ids_seen.max(initial=-1)}); pose rows must be the run's frame ids")
    if truth.pairs.max(initial=-1) >= n_frames:
        log.warning("%s names frames up to %d but the run has %d frames", truth.path, truth.pairs.max(), n_frames)

    skipped: list[str] = []
    det = loops[:, :2].astype(np.int64)
    correct = correct_mask(det, truth.pairs)
    op = precision_recall(det, truth.pairs)
    report: dict[str, Any] = {
        "format_version": FORMAT_VERSION, "run": str(run_dir), "loops_csv": str(loops_csv),
        "ground_truth": {"path": str(truth.path), "kind": truth.kind, "pairs": len(truth.pairs),
                         "queries_with_loop": len(truth.queries), "frames": n_frames,
                         **({"radius": radius, "min_gap": min_gap, "min_gap_s": min_gap_s if timestamps is not None
                             else None} if truth.kind == "poses" else {})},
        "operating_point": {**op.as_dict(), "min_inliers": policy.get("min_inliers"),
                            "min_matches": policy.get("min_matches"),
                            "false_detections": det[~correct].tolist()},
        "pr_curve": None, "retrieval": None, "plots": {}, "skipped": skipped,
    }

    curve = None
    if cands is not None:
        accepted = cands[cands[:, 5] > 0][:, :2].astype(np.int64)
        if set(map(tuple, accepted.tolist())) != set(map(tuple, det.tolist())):
            log.warning("candidates.csv 'accepted' rows differ from loops.csv; the operating point uses loops.csv")
        min_matches = int(policy.get("min_matches") or 0)
        best, best_scores = best_per_query(cands, score, min_matches)
        curve = pr_curve(best, best_scores, truth.pairs)
        r100, t100 = curve.max_recall_at_precision_1()
        report["pr_curve"] = {"score": score, "min_matches": min_matches, "auc_method": "average_precision",
                              "auc": _num(curve.average_precision()), "max_recall_at_100_precision": _num(r100),
                              "threshold_at_100_precision": t100, **curve.as_dict()}
        rk = recall_at_k(cands, truth.pairs, KS)
        k_searched = (run_conf.get("search") or {}).get("k")
        if k_searched is not None and max(KS) > int(k_searched):
            log.info("the run kept only %s candidates per query: Recall@k for k > %s equals Recall@%s",
                     k_searched, k_searched, k_searched)
        report["retrieval"] = {"recall_at_k": {str(k): _num(v) for k, v in rk.items()},
                               "k_searched": k_searched,
                               "queries_with_loop": len(truth.queries)}
        report["plots"]["pr_curve"] = str(plot_pr_curve(curve, out / "pr_curve.png", score, op, run_dir.name))
    else:
        skipped += ["pr_curve", "retrieval"]
        log.info("no candidates.csv beside %s: PR curve and Recall@k skipped", loops_csv)

    poses = truth.poses
    if poses is None and (seq_poses := _sequence_file(summary, "poses")) is not None:
        try:
            poses = read_kitti_poses(seq_poses)
        except (OSError, ValueError) as err:  # ConfigError is a ValueError
            log.warning("cannot use the sequence poses %s: %s", seq_poses, err)
        if poses is not None and len(poses) != n_frames:
            log.warning("%s has %d poses for %d frames; not used", seq_poses, len(poses), n_frames)
            poses = None
    codes = None
    if kf_path.is_file():
        codes, kf_ids, kf_poses = _keyframes(kf_path)
        if poses is None and np.isfinite(kf_poses).all(axis=(1, 2)).any():
            poses = np.full((n_frames, 3, 4), np.nan)
            ok = kf_ids < n_frames
            poses[kf_ids[ok]] = kf_poses[ok]
    title = f"{run_dir.name} vs {truth.path.name}"
    if poses is not None:
        report["plots"]["trajectory"] = str(plot_trajectory(poses, out / "trajectory.png", truth.pairs, det,
                                                            correct, title))
    else:
        skipped.append("trajectory")
        log.info("no poses known for the run (ground truth is a pairs file, none beside the sequence or in "
                 "keyframes.h5): trajectory plot skipped")
    if codes is not None:
        report["plots"]["similarity"] = str(plot_similarity(codes, kf_ids, n_frames, truth.pairs,
                                                            out / "similarity.png", det, correct, title))
    else:
        skipped.append("similarity")
        log.info("no keyframes.h5 beside %s: similarity plot skipped", loops_csv)

    (out / "evaluation.json").write_text(json.dumps(report, indent=1))
    _log_report(report)
    log.info("wrote %s", ", ".join([str(out / "evaluation.json"), *report["plots"].values()]))
    return report


def _num(v: float) -> float | None:
    return None if v is None or np.isnan(v) else float(v)


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _log_report(r: dict[str, Any]) -> None:
    g, op = r["ground_truth"], r["operating_point"]
    log.info("ground truth %s (%s): %d pairs, %d queries with a loop", g["path"], g["kind"], g["pairs"],
             g["queries_with_loop"])
    log.info("%-34s %s (%d/%d)", "precision @ operating point", _fmt(op["precision"]), op["true_positives"],
             op["detections"])
    log.info("%-34s %s (%d of %d queries)", "recall @ operating point", _fmt(op["recall"]), op["true_positives"],
             op["positives"])
    if r["pr_curve"]:
        pc = r["pr_curve"]
        t100 = pc["threshold_at_100_precision"]
        t = "" if t100 is None else f" ({pc['score']} >= {t100:g})"
        log.info("%-34s %s%s", "max recall @ 100% precision", _fmt(pc["max_recall_at_100_precision"]), t)
        log.info("%-34s %s", f"AUC (average precision, {pc['score']})", _fmt(pc["auc"]))
    if r["retrieval"]:
        log.info("%-34s %s", "retrieval Recall@1 / @5 / @10",
                 " / ".join(_fmt(v) for v in r["retrieval"]["recall_at_k"].values()))


_DEFAULTS = api_defaults(main)


def add_parser(sub: Any) -> None:
    p = sub.add_parser("evaluate", help="evaluate a detect run against ground truth (PR, AUC, Recall@k, plots)",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="run folder written by 'cae-lcd detect', or a loops.csv")
    p.add_argument("--gt", required=True, help="ground truth: 'i j' pairs file (0-based) or KITTI poses file")
    p.add_argument("--out", help="folder for evaluation.json and the PNGs (default: the run folder)")
    p.add_argument("--radius", type=float, default=_DEFAULTS["radius"],
                   help="poses ground truth: loop radius on the x-z plane, metres (default %(default)s)")
    p.add_argument("--min-gap", type=int, default=_DEFAULTS["min_gap"],
                   help="poses ground truth: minimum frame gap (default %(default)s)")
    p.add_argument("--min-gap-s", type=float, default=_DEFAULTS["min_gap_s"],
                   help="poses ground truth: minimum time gap in seconds, replaces --min-gap (needs times)")
    p.add_argument("--times", help="times.txt for --min-gap-s (default: the run's sequence's times.txt)")
    p.add_argument("--score", choices=SCORES, default=_DEFAULTS["score"],
                   help="score swept for the PR curve (default %(default)s)")
    p.set_defaults(func=_run)


def _run(args: Any) -> None:
    main(Path(args.run), Path(args.gt), None if args.out is None else Path(args.out), args.radius, args.min_gap,
         args.min_gap_s, args.score, None if args.times is None else Path(args.times))
