"""Shared pieces of ``cae-lcd bench``: the time budget, detection runs (optionally in a fresh process, for a clean
peak-memory reading), a sequence's ground truth, the metrics of a run, and Markdown tables."""

from __future__ import annotations

import argparse
import logging
import multiprocessing
import resource
import shutil
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.evaluation.evaluate import KS
from cae_lcd.evaluation.ground_truth import read_loop_pairs
from cae_lcd.evaluation.metrics import best_per_query, pr_curve, precision_recall, recall_at_k
from retrieval.run_folder import CANDIDATE_COLUMNS, RunFolder, read_csv_table
from retrieval.sequences import open_sequence

__all__ = ["Budget", "detect_run", "ground_truth_pairs", "run_metrics", "md_table", "fmt", "REPO", "season_frames",
           "study_parser", "work_study_cli"]

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]  #: the project checkout (configs/ lives here)


class Budget:
    """Wall-clock budget of one bench run: what is left decides whether optional parts still run."""

    def __init__(self, seconds: float) -> None:
        self.seconds = float(seconds)
        self.start = time.perf_counter()

    def elapsed(self) -> float:
        """Seconds since the bench started."""
        return time.perf_counter() - self.start

    def left(self) -> float:
        """Seconds left (negative once overrun)."""
        return self.seconds - self.elapsed()

    def allows(self, estimate_s: float) -> bool:
        """True when an estimated ``estimate_s`` seconds still fit."""
        return estimate_s <= self.left()


def _detect_child(path: str, out: str, conf: dict[str, Any], options: dict[str, Any]) -> tuple[dict[str, Any], int]:
    """Runs ``retrieval.detect.main`` in this (fresh) process; returns its summary and peak RSS in bytes."""
    import retrieval.baselines  # noqa: F401  (registers the baseline descriptors)
    from retrieval.detect import main as detect

    summary = detect(path, out, conf, progress=False, **options)
    return summary, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def detect_run(path: str | Path, out: str | Path, conf: dict[str, Any] | None = None,
               isolate: bool = False, **options: Any) -> dict[str, Any]:
    """A fresh ``cae-lcd detect`` run (the run folder is emptied first).

    Args:
        path: sequence folder.
        out: run folder (deleted and rewritten).
        conf: detector overrides.
        isolate: run in a freshly spawned process, so that ``peak_rss_bytes`` is the detector's own peak memory
            (resident set size: numpy and torch buffers included) and not this process's.
        options: ``retrieval.detect.main``'s other keyword arguments (``camera_info``, ``intrinsics``, ...).

    Returns:
        ``retrieval.detect.main``'s summary plus ``wall_s`` and, when isolated, ``peak_rss_bytes``.
    """
    out = Path(out)
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    if isolate:
        with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
            summary, rss = pool.submit(_detect_child, str(path), str(out), conf or {}, options).result()
        summary["peak_rss_bytes"] = rss
    else:
        import retrieval.baselines  # noqa: F401
        from retrieval.detect import main as detect

        summary = detect(path, out, conf or {}, progress=False, **options)
    summary["wall_s"] = time.perf_counter() - t0
    return summary


def ground_truth_pairs(sequence: str | Path) -> np.ndarray | None:
    """The ``(P, 2)`` true loop pairs of a sequence (its ``loops.txt``), or None when it has none."""
    gt = open_sequence(sequence).ground_truth
    return None if gt is None else read_loop_pairs(gt)


def run_metrics(out: str | Path, ground_truth: np.ndarray | None, min_matches: int,
                score: str = "inliers") -> dict[str, Any]:
    """Operating point, max recall at 100 % precision (sweep on ``score``) and retrieval Recall@k of a run folder.

    Args:
        out: run folder written by ``retrieval.detect.main``.
        ground_truth: ``(P, 2)`` true pairs, or None (then only the loop count is known).
        min_matches: the run's ``policy.min_matches`` (candidates below it are ineligible in the sweep).
        score: one of ``cae_lcd.evaluation.metrics.SCORES`` (``"confidence"``, ``"inliers"``, ``"cosine"``, ``"seq_score"``).

    Returns:
        ``loops``, ``ms_total`` (median end-to-end ms/frame) and ``score``; with ground truth also the operating
        point (``PRResult.as_dict()``: precision, recall, true_positives, ...), ``r100``, ``t100`` and
        ``recall_at_k``.
    """
    run = RunFolder(Path(out))
    loops = run.read_loops()[:, :2].astype(np.int64)
    ms_total = run.read_summary().get("ms_per_frame", {}).get("total", {}).get("median")
    res: dict[str, Any] = {"loops": len(loops), "ms_total": ms_total, "score": score}
    if ground_truth is None:
        return res
    cands = read_csv_table(run.candidates, CANDIDATE_COLUMNS)  # detect always writes it: missing is an error
    best, scores = best_per_query(cands, score, min_matches)
    r100, t100 = pr_curve(best, scores, ground_truth).max_recall_at_precision_1()
    res.update(precision_recall(loops, ground_truth).as_dict())
    res.update({"r100": r100, "t100": t100, "recall_at_k": recall_at_k(cands, ground_truth, KS)})
    return res


def fmt(v: Any, digits: int = 3) -> str:
    """A table cell: floats rounded, None/nan as ``n/a``."""
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def season_frames(root: Path, season: str) -> list[Path]:
    """The images of one season, as the data set's ``frames.txt`` names them (``index season source``)."""
    rows = [line.split() for line in (root / "frames.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    frames = sorted((root / "images").glob("*.png"))
    picked = [frames[int(r[0])] for r in rows if len(r) >= 2 and r[1] == season and int(r[0]) < len(frames)]
    if not picked:
        raise ConfigError(f"{root / 'frames.txt'} names no {season} frame")
    return picked


def md_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A GitHub Markdown table (cells through ``fmt`` unless already strings)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(c if isinstance(c, str) else fmt(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def study_parser(doc: str, run_dir: str) -> argparse.ArgumentParser:
    """The command line every ``python -m bench.<study>`` shares: ``--data`` (the datasets), ``--run-dir`` (its run
    folders, default ``run_dir``) and ``--out`` (the Markdown file its sections go to; '' = none)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "datasets")
    ap.add_argument("--run-dir", type=Path, default=Path(run_dir))
    ap.add_argument("--out", default=str(REPO / "BENCHMARKS.md"), help="Markdown file to update ('' = none)")
    return ap


def work_study_cli(main: Callable[[str, bool], Any], doc: str, out: str) -> None:
    """The command line of a study with its own work folder that rewrites its BENCHMARKS.md section:
    ``--out`` (the work folder, default ``out``; rewritten) and ``--no-write``; runs ``main(out, write)``."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--out", default=out, help="work folder (rewritten)")
    ap.add_argument("--no-write", action="store_true", help="do not rewrite BENCHMARKS.md")
    args = ap.parse_args()
    main(args.out, not args.no_write)
