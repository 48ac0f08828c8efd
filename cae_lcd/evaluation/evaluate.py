"""Evaluate a detect run against ground truth (``cae-lcd evaluate RUN_DIR_OR_LOOPS_CSV --gt GROUND_TRUTH``).

Reports precision/recall per query at the operating point, the PR curve swept over the verification score (max
recall at 100 % precision, AUC as average precision), and Recall@1/5/10 of the retrieval stage alone. Writes
``evaluation.json`` (``format_version`` 1) and ``pr_curve.png``, ``trajectory.png``, ``similarity.png``, and the
montages ``loops_montage.png`` (accepted loops, wrong ones framed red) and ``missed_montage.png``
(``cae_lcd.evaluation.montage``).
Everything read is checked first: a damaged table, summary or ground truth is an error or a warning, never a
wrong figure.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from retrieval.database import KeyframeDatabase
from retrieval.run_folder import CANDIDATE_COLUMNS, LOOPS_COLUMNS, RunFolder, read_csv_table
from retrieval.sequences import kitti_metadata_file, open_sequence, read_kitti_poses, read_times

from .ground_truth import WORLDS, GroundTruth, in_run_ids, load_ground_truth, sniff_ground_truth
from .metrics import SCORES, best_per_query, correct_mask, pr_curve, precision_recall, recall_at_k

__all__ = ["FORMAT_VERSION", "KS", "main", "score_run"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
KS = (1, 5, 10)  #: Recall@k cut-offs
MAX_PLOTTED_FRAMES = 200_000  #: larger runs get no trajectory/similarity plot (the report is still complete)


def score_run(run_dir: str | Path, gt: str | Path, world: str = "auto") -> dict[str, Any]:
    """Adds the operating point against ``gt`` to a run's ``summary.json`` (as ``"ground_truth"``, and the world
    convention as ``"world"`` for a later ``evaluate``).

    Args:
        run_dir: a run folder written by ``retrieval.detect.main``.
        gt: pairs file or KITTI poses file (``load_ground_truth`` defaults).
        world: the poses' world convention (``cae_lcd.evaluation.ground_truth.WORLDS``).

    Returns:
        The updated summary.
    """
    run = RunFolder(Path(run_dir))
    summary = run.read_summary()
    truth = _source_numbered(load_ground_truth(gt, world=world), gt, summary)
    pairs = read_csv_table(run.loops, LOOPS_COLUMNS[:2]).astype(np.int64)
    summary["ground_truth"] = precision_recall(pairs, truth.pairs).as_dict()
    summary["world"] = world
    run.write_summary(summary)
    return summary


def _read_run_conf(path: Path) -> dict[str, Any]:
    """The run's resolved conf; ``{}`` (with a warning) when missing or unreadable."""
    if not path.is_file():
        return {}
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError):
        log.warning("cannot read %s; evaluating without the run's conf", path)
        return {}
    if not isinstance(data, dict):
        log.warning("%s is not a mapping; evaluating without the run's conf", path)
        return {}
    return data


def _section_int(conf: dict[str, Any], section: str, key: str) -> int | None:
    value = (conf.get(section) if isinstance(conf.get(section), dict) else {}).get(key)
    return value if isinstance(value, int) and not isinstance(value, bool) and value >= 0 else None


def _resolve_run(run: Path) -> tuple[Path, Path]:
    run = Path(run)
    if run.is_dir():
        folder = RunFolder(run)
        if not folder.loops.is_file():
            raise ConfigError(f"{run} holds no loops.csv; pass a run folder written by 'cae-lcd detect' or a loops.csv")
        return run, folder.loops
    if run.is_file():
        return run.parent, run
    raise ConfigError(f"run not found: {run}")


def _load_truth(gt: Path, radius: float, min_gap: int, min_gap_s: float | None, times: Path | None,
                summary: dict[str, Any], world: str = "auto") -> tuple[GroundTruth, bool]:
    """The ground truth (``world``: "auto" takes the one ``detect`` scored with, when it said), and whether a time
    gap was used."""
    if world == "auto" and summary.get("world") in WORLDS:
        world = summary["world"]
    timestamps = None
    if min_gap_s is not None and sniff_ground_truth(gt) == "poses":
        sequence = summary.get("sequence")
        tpath = Path(times) if times is not None else (
            kitti_metadata_file(sequence, "times") if isinstance(sequence, str) else None)
        if tpath is None:
            raise ConfigError("--min-gap-s needs timestamps: pass --times, or run on a sequence with times.txt")
        timestamps = read_times(tpath)
    return _source_numbered(load_ground_truth(gt, radius, min_gap, timestamps, min_gap_s, world), gt, summary), \
        timestamps is not None


def _source_numbered(truth: GroundTruth, gt: str | Path, summary: dict[str, Any]) -> GroundTruth:
    """``truth`` in the run's frame ids: a run of every n-th frame of a video (``summary["stride"]``) scored against
    a ground truth given in the video's own frame numbers (not the one ``detect`` wrote for the run itself)."""
    stride = summary.get("stride", 1)
    own = summary.get("ground_truth_file")
    if not isinstance(stride, int) or stride <= 1 or (isinstance(own, str) and Path(own) == Path(gt)):
        return truth
    return in_run_ids(truth, stride)


def _frame_count(summary: dict[str, Any], ids_seen: np.ndarray, truth: GroundTruth) -> int:
    """Frames of the run: from the summary when it says, else the largest id seen; checked against the tables."""
    frames = summary.get("frames")
    top = int(ids_seen.max(initial=-1))
    if isinstance(frames, int) and not isinstance(frames, bool) and frames >= 0:
        if top >= frames:
            raise ConfigError(f"the run's tables name frame {top} but its summary.json says {frames} frames; the "
                              "run folder is inconsistent (damaged or mixed from two runs)")
        n_frames = frames
    else:
        if frames is not None:
            log.warning("summary.json 'frames' is %r, not a count; using the tables' largest frame id", frames)
        n_frames = int(max(top, truth.pairs.max(initial=-1)) + 1)
    if truth.kind == "poses" and (len(truth.poses) != n_frames if isinstance(frames, int) else top >= len(truth.poses)):
        raise ConfigError(f"{truth.path} has {len(truth.poses)} poses but the run has {n_frames} frames "
                          f"(frame ids up to {top}); pose rows must be the run's frame ids")
    if truth.pairs.max(initial=-1) >= n_frames:
        log.warning("%s names frames up to %d but the run has %d frames", truth.path, truth.pairs.max(), n_frames)
    return n_frames


def _pr_section(cands: np.ndarray, det: np.ndarray, truth: GroundTruth, score: str,
                run_conf: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any], Any]:
    """PR curve over the swept score and retrieval Recall@k, from candidates.csv."""
    accepted = cands[cands[:, CANDIDATE_COLUMNS.index("accepted")] > 0][:, :2].astype(np.int64)
    if set(map(tuple, accepted.tolist())) != set(map(tuple, det.tolist())):
        log.warning("candidates.csv 'accepted' rows differ from loops.csv; the operating point uses loops.csv")
    min_matches = _section_int(run_conf, "policy", "min_matches") or 0
    best, best_scores = best_per_query(cands, score, min_matches)
    curve = pr_curve(best, best_scores, truth.pairs)
    r100, t100 = curve.max_recall_at_precision_1()
    section = {"score": score, "min_matches": min_matches, "auc_method": "average_precision",
               "auc": _num(curve.average_precision()), "max_recall_at_100_precision": _num(r100),
               "threshold_at_100_precision": t100, **curve.as_dict()}
    k_searched = _section_int(run_conf, "search", "k")
    if k_searched is not None and max(KS) > k_searched:
        log.info("the run kept only %s candidates per query: Recall@k for k > %s equals Recall@%s",
                 k_searched, k_searched, k_searched)
    retrieval = {"recall_at_k": {str(k): _num(v) for k, v in recall_at_k(cands, truth.pairs, KS).items()},
                 "k_searched": k_searched, "queries_with_loop": len(truth.queries)}
    return section, retrieval, curve


def _run_poses(truth: GroundTruth, summary: dict[str, Any], n_frames: int,
               kf: tuple[np.ndarray | None, np.ndarray, np.ndarray] | None) -> np.ndarray | None:
    """Poses for the trajectory plot: the ground truth's, the sequence's, or those stored with the keyframes."""
    if truth.poses is not None:
        return truth.poses
    sequence = summary.get("sequence")
    seq_poses = kitti_metadata_file(sequence, "poses") if isinstance(sequence, str) else None
    if seq_poses is not None:
        try:
            poses = read_kitti_poses(seq_poses)
        except ConfigError as err:
            log.warning("cannot use the sequence poses: %s", err)
        else:
            if len(poses) == n_frames:
                return poses
            log.warning("%s has %d poses for %d frames; not used", seq_poses, len(poses), n_frames)
    if kf is not None and np.isfinite(kf[2]).all(axis=(1, 2)).any():
        poses = np.full((n_frames, 3, 4), np.nan)
        ok = kf[1] < n_frames
        poses[kf[1][ok]] = kf[2][ok]
        return poses
    return None


def _keyframes(path: Path) -> tuple[np.ndarray | None, np.ndarray, np.ndarray] | None:
    """Codes ``(n, D)`` (None when the keyframes hold binary descriptors, as MILD's do), frame ids ``(n,)`` and poses
    ``(n, 3, 4)`` (NaN when unknown) from ``keyframes.h5``."""
    if not path.is_file():
        return None
    with KeyframeDatabase(path, mode="r") as db:
        entries = [(fid, code) for fid, code, _, _ in db.search_entries()]
        poses = db.poses()
    ids = np.array([fid for fid, _ in entries], np.int64)
    if any(code.ndim != 1 for _, code in entries):
        return None, ids, poses
    codes = np.stack([code for _, code in entries]).astype(np.float32) if entries else np.zeros((0, 1), np.float32)
    return codes, ids, poses


def _plots(report: dict[str, Any], out: Path, title: str, truth: GroundTruth, det: np.ndarray,
           correct: np.ndarray, n_frames: int, poses: np.ndarray | None,
           kf: tuple[np.ndarray | None, np.ndarray, np.ndarray] | None) -> None:
    from .plots import plot_similarity, plot_trajectory  # matplotlib only when evaluating

    if n_frames > MAX_PLOTTED_FRAMES:
        report["skipped"] += ["trajectory", "similarity"]
        log.info("%d frames: trajectory and similarity plots skipped (limit %d)", n_frames, MAX_PLOTTED_FRAMES)
        return
    if poses is not None:
        report["plots"]["trajectory"] = str(plot_trajectory(poses, out / "trajectory.png", truth.pairs, det,
                                                            correct, title, 1 if truth.up is None else truth.up))
    else:
        report["skipped"].append("trajectory")
        log.info("no poses known for the run (ground truth is a pairs file, none beside the sequence or in "
                 "keyframes.h5): trajectory plot skipped")
    if kf is not None and kf[0] is not None:
        report["plots"]["similarity"] = str(plot_similarity(kf[0], kf[1], n_frames, truth.pairs,
                                                            out / "similarity.png", det, correct, title))
    else:
        report["skipped"].append("similarity")
        if kf is not None:
            log.info("the keyframes hold binary descriptors (MILD), not codes: similarity plot skipped")
        log.info("no keyframes.h5 in the run folder: similarity plot skipped")


def _montages(report: dict[str, Any], out: Path, summary: dict[str, Any], det: np.ndarray, correct: np.ndarray,
              truth: GroundTruth, title: str) -> None:
    """``loops_montage.png`` and ``missed_montage.png`` (``cae_lcd.evaluation.montage``) from the run's sequence
    frames."""
    from .montage import missed_pairs, write_montage

    sequence = summary.get("sequence")
    try:
        frames = open_sequence(sequence).frames if isinstance(sequence, str) else []
    except ConfigError as err:
        log.info("the run's sequence cannot be read (%s): montages skipped", err)
        frames = []
    ids = np.concatenate([det.ravel(), truth.pairs.ravel()])
    if not frames or (len(ids) and ids.max() >= len(frames)):
        report["skipped"] += ["loops_montage", "missed_montage"]
        log.info("the run's frames are not where summary.json says: montages skipped")
        return
    report["plots"]["loops_montage"] = str(write_montage(out / "loops_montage.png", frames, det, correct,
                                                         title=f"accepted loops, {title}"))
    report["plots"]["missed_montage"] = str(write_montage(out / "missed_montage.png", frames,
                                                          missed_pairs(det, correct, truth.pairs), missed=True,
                                                          title=f"missed loops, {title}"))


def _check_args(radius: float, min_gap: int, min_gap_s: float | None, score: str) -> None:
    if score not in SCORES:
        raise ConfigError(f"unknown score '{score}'; choose one of {', '.join(SCORES)}")
    if not (np.isfinite(radius) and radius > 0):
        raise ConfigError(f"--radius must be a finite number > 0; got {radius}")
    if min_gap < 0:
        raise ConfigError(f"--min-gap must be >= 0; got {min_gap}")
    if min_gap_s is not None and not (np.isfinite(min_gap_s) and min_gap_s >= 0):
        raise ConfigError(f"--min-gap-s must be a finite number >= 0; got {min_gap_s}")


def main(run: Path, gt: Path | None = None, out: Path | None = None, radius: float = 5.0, min_gap: int = 50,
         min_gap_s: float | None = None, score: str = "confidence", times: Path | None = None,
         world: str = "auto") -> dict[str, Any]:
    """Evaluates a detect run against ground truth and writes the report and plots.

    Args:
        run: run folder written by ``cae-lcd detect``, or a ``loops.csv`` file (then only the operating point is
            computed unless ``candidates.csv`` / ``keyframes.h5`` lie beside it).
        gt: pairs file (``i j`` a line, 0-based) or KITTI poses file (12 numbers a line; row = frame id); None =
            the ground truth ``detect`` found for the run's sequence (``summary.json`` ``ground_truth_file``: its
            ``loops.txt``, or the poses of a TUM / EuRoC recording, from which the loops are derived).
        out: folder for ``evaluation.json`` and the PNGs; None = the run folder.
        radius: metres, for pose-derived ground truth.
        min_gap: minimum frame gap, for pose-derived ground truth.
        min_gap_s: minimum time gap (seconds) instead of ``min_gap``; needs timestamps (``times`` or the run's
            sequence ``times.txt``).
        score: the score the PR curve sweeps (``cae_lcd.evaluation.metrics.SCORES``): ``"confidence"`` (what the
            detector thresholds), ``"inliers"``, ``"cosine"`` or ``"seq_score"``.
        times: ``times.txt`` (one timestamp a frame) for ``min_gap_s``; None = the run's sequence's.
        world: a poses ground truth's world convention (``cae_lcd.evaluation.ground_truth.WORLDS``): ``"auto"``
            takes the one the run was scored with, else finds the gravity axis from the trajectory.

    Returns:
        The report written to ``evaluation.json``.

    Raises:
        ConfigError: bad arguments, unreadable or inconsistent run files or ground truth.
        DatabaseError: a damaged ``keyframes.h5``.
    """
    _check_args(radius, min_gap, min_gap_s, score)
    run_dir, loops_csv = _resolve_run(run)
    folder = RunFolder(run_dir)
    summary, run_conf = folder.read_summary(), _read_run_conf(folder.conf)
    if gt is None:
        gt = summary.get("ground_truth_file")
        if not isinstance(gt, str):
            raise ConfigError(f"{run_dir}: its sequence has no ground truth (no loops.txt, no ground-truth poses); "
                              "pass --gt")
    truth, used_time = _load_truth(Path(gt), radius, min_gap, min_gap_s, times, summary, world)
    loops = read_csv_table(loops_csv, LOOPS_COLUMNS[:2])  # the pairs are all the operating point needs
    cands = folder.read_candidates()
    ids_seen = np.concatenate([loops[:, :2].ravel(), [] if cands is None else cands[:, :2].ravel()]).astype(np.int64)
    n_frames = _frame_count(summary, ids_seen, truth)
    kf = _keyframes(folder.database)  # read (and checked) before anything is written
    out = prepare_out_dir(out if out is not None else run_dir)

    det = loops[:, :2].astype(np.int64)
    correct = correct_mask(det, truth.pairs)
    op = precision_recall(det, truth.pairs)
    gap = {"radius": radius, "min_gap": min_gap, "min_gap_s": min_gap_s if used_time else None}
    report: dict[str, Any] = {
        "format_version": FORMAT_VERSION, "run": str(run_dir), "loops_csv": str(loops_csv),
        "ground_truth": {"path": str(truth.path), "kind": truth.kind, "pairs": len(truth.pairs),
                         "queries_with_loop": len(truth.queries), "frames": n_frames,
                         **(gap if truth.kind == "poses" else {})},
        "operating_point": {**op.as_dict(), "min_inliers": _section_int(run_conf, "policy", "min_inliers"),
                            "min_matches": _section_int(run_conf, "policy", "min_matches"),
                            "false_detections": det[~correct].tolist()},
        "pr_curve": None, "retrieval": None, "plots": {}, "skipped": [],
    }
    if cands is not None:
        from .plots import plot_pr_curve

        report["pr_curve"], report["retrieval"], curve = _pr_section(cands, det, truth, score, run_conf)
        report["plots"]["pr_curve"] = str(plot_pr_curve(curve, out / "pr_curve.png", score, op, run_dir.name))
    else:
        report["skipped"] += ["pr_curve", "retrieval"]
        log.info("no candidates.csv beside %s: PR curve and Recall@k skipped", loops_csv)
    poses = _run_poses(truth, summary, n_frames, kf)
    _plots(report, out, f"{run_dir.name} vs {truth.path.name}", truth, det, correct, n_frames, poses, kf)
    _montages(report, out, summary, det, correct, truth, f"{run_dir.name} vs {truth.path.name}")
    write_text_atomic(out / "evaluation.json", json.dumps(report, indent=1))
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
