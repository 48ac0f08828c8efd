"""``cae-lcd detect`` by default against the API stream (issue 27): ``python -m bench.online_detect [--out
runs/bench/online_detect] [--no-write]`` (the shared datasets beside the repository).

``detect`` calibrates itself on the stream by default (``calibration.online``, ``retrieval.online``), the algorithm
``LoopDetector.process`` runs through the API. For KITTI 90 and Nordland: ``detect``'s loops (its own and the delayed
ones, ``loops.csv``) and the API stream's (``bench.aliasing.stream_run``: one frame at a time, no store), their
precision / recall, whether the two sets of loops are the same, and the milliseconds a frame of each (``detect``: its
frames' wall time, the stream's own calibration inside it apart; the whole run's wall time a frame, its loop edges
included and their share apart, against one SIFT extraction at 512 px measured in the same run,
``bench.frame_time.sift_yardstick``: the yardstick issue 27 sets; the stream: the mean, refits amortised, and its
worst frame). Rewrites the
``bench:online-detect`` section of BENCHMARKS.md.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cae_lcd.core.threads import cpu_count
from cae_lcd.evaluation.ground_truth import read_loop_pairs
from cae_lcd.evaluation.metrics import precision_recall
from retrieval.run_folder import RunFolder
from retrieval.sequences import open_sequence

from .aliasing import stream_run
from .common import REPO, detect_run, md_table, work_study_cli
from .frame_time import sift_yardstick
from .run import write_section

__all__ = ["SETS", "compare", "main"]

log = logging.getLogger(__name__)

YARDSTICK_FRAMES = 50  #: frames (spread over the set) the SIFT yardstick is timed on
SETS = {"KITTI 90": ("kitti", "sequences", "90"), "Nordland summer -> winter (64x32)": ("nordland",)}  #: set -> path


def compare(folder: Path, run_dir: Path) -> dict[str, Any]:
    """One set: ``detect`` (default conf) into ``run_dir`` and the API stream, scored against ``folder/loops.txt``."""
    truth = read_loop_pairs(folder / "loops.txt")
    seq = open_sequence(folder)
    images = [seq.read_frame(i)[0] for i in range(0, len(seq), max(1, len(seq) // YARDSTICK_FRAMES))]
    sift_ms, sift_cores_ms = sift_yardstick(images), sift_yardstick(images, cpu_count())
    summary = detect_run(folder, run_dir)
    written = RunFolder(run_dir).read_loops()[:, :2].astype(np.int64)
    stream = stream_run(folder, truth)
    pr = precision_recall(written, truth)
    sec = summary["seconds"]
    return {"frames": summary["frames"], "detect_loops": len(written), "precision": pr.precision,
            "recall": pr.recall, "stream_loops": stream["loops"], "stream_precision": stream["precision"],
            "stream_recall": stream["recall"], "stream_r10": stream["r10"],
            "same": set(map(tuple, written.tolist())) == set(map(tuple, stream["pairs"].tolist())),
            "detect_ms": 1e3 * sec["frames"] / max(summary["frames"], 1),
            "detect_calibration_ms": 1e3 * sec.get("calibration_online", 0.0) / max(summary["frames"], 1),
            "detect_whole_ms": 1e3 * summary["wall_s"] / max(summary["frames"], 1), "sift_ms": sift_ms,
            "sift_cores_ms": sift_cores_ms,
            "detect_edges_ms": 1e3 * sec.get("loop_edges", 0.0) / max(summary["frames"], 1),
            "stream_ms": stream["ms_mean"], "stream_worst_ms": stream["ms_worst"]}


def main(out: str | Path = "runs/bench/online_detect", write: bool = True) -> dict[str, dict[str, Any]]:
    """Every set of ``SETS`` (run folders under ``out``); logs the table, writes it into BENCHMARKS.md (``write``),
    returns the rows by set."""
    data, run_dir = REPO.parent / "shared" / "datasets", Path(out)
    rows = {name: compare(data.joinpath(*parts), run_dir / f"run_{i}") for i, (name, parts) in enumerate(SETS.items())}
    table = md_table(["set", "frames", "detect loops", "precision / recall", "API stream loops",
                      "precision / recall", "same loops", "detect ms/frame (own calibration)",
                      "detect whole run ms/frame (loop edges) / one SIFT at 512 px on one core (on every core)",
                      "stream ms/frame (worst frame)"],
                     [[name, str(m["frames"]), str(m["detect_loops"]), f"{m['precision']:.3f} / {m['recall']:.3f}",
                       str(m["stream_loops"]), f"{m['stream_precision']:.3f} / {m['stream_recall']:.3f}",
                       "yes" if m["same"] else "NO", f"{m['detect_ms']:.1f} ({m['detect_calibration_ms']:.1f})",
                       f"{m['detect_whole_ms']:.1f} ({m['detect_edges_ms']:.1f}) / {m['sift_ms']:.1f} = "
                       f"{m['detect_whole_ms'] / m['sift_ms']:.1f}x ({m['sift_cores_ms']:.1f}: "
                       f"{m['detect_whole_ms'] / m['sift_cores_ms']:.1f}x)",
                       f"{m['stream_ms']:.1f} ({m['stream_worst_ms']:.0f})"] for name, m in rows.items()])
    log.info("\n%s", table)
    if write:
        write_section(REPO / "BENCHMARKS.md", "`python -m bench.online_detect`: `cae-lcd detect` with the default conf "
                      "(the online path: the stream calibrates itself) against the same frames streamed through the API "
                      "(`LoopDetector.process`, no store). Same loops: the two sets of (query, reference) pairs are "
                      "equal. ms/frame: `detect`'s frames' wall time a frame (its own calibration's share in brackets); "
                      "its whole run's (`retrieval.detect.main`: calibration, frames, loop edges, the edges' share in "
                      "brackets; process start-up excluded) against one SIFT extraction at 512 px in the same run "
                      "(issue 27 asks at most 1x), OpenCV on one core and, in brackets, on every core (its default); "
                      "the stream's mean a frame, refits amortised (its worst frame in brackets).\n\n" + table,
                      "online-detect")
    return rows


if __name__ == "__main__":
    work_study_cli(main, __doc__, "runs/bench/online_detect")
