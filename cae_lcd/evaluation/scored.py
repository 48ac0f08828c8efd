"""One sequence, detected and scored: what ``cae-lcd detect PATH`` does for each sequence (alone, or as one Ray task
of many): ``retrieval.detect.main``, then precision/recall against the sequence's ground truth when it has one."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from retrieval import detect
from retrieval.sequences import open_sequence

from .evaluate import score_run
from .ground_truth import check_world, load_ground_truth

__all__ = ["detect_and_score"]


def detect_and_score(path: str | Path | None, out: str | Path | None, conf: dict[str, Any] | None = None,
                     camera: str | None = None, progress: bool = True, topic: str | None = None,
                     stride: int = 1, intrinsics: str | None = None,
                     camera_info: str | Path | None = None, world: str = "auto",
                     metric_from_poses: bool = False, edge_frame: str = "camera") -> dict[str, Any]:
    """``detect.main`` on one sequence (same arguments), then the operating point against its ground truth (its
    ``loops.txt``, or loops derived from TUM / EuRoC poses across the gravity axis of ``world``: ``WORLDS``) added
    to the summary.

    Returns:
        The run's summary (``summary.json``), with ``ground_truth`` when the sequence has one.

    Raises:
        ConfigError: as ``detect.main``; a broken ground-truth file is refused before anything is written.
    """
    check_world(world)  # refused before anything is written
    seq = open_sequence(detect.SAMPLE_DIR if path is None else path, camera, topic, stride)
    if seq.ground_truth is not None:
        load_ground_truth(seq.ground_truth)
    summary = detect.main(seq, out, conf, progress=progress, intrinsics=intrinsics, camera_info=camera_info,
                          metric_from_poses=metric_from_poses, edge_frame=edge_frame)  # opened once: each reader warning said once
    if summary.get("ground_truth_file"):
        summary = score_run(summary["out"], summary["ground_truth_file"], world)
    return summary
