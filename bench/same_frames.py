"""Every frame's result through the API, written as text, to compare two versions of the code bit for bit:
``python -m bench.same_frames FOLDER OUT.json [--frames N]``.

A change meant to be faster and nothing else (a cache, a batched call, another reduction) must leave every decision
as it was. This streams a sequence folder through ``LoopDetector.process`` from frame 0 (the default conf, the stream
calibrating itself) and writes, for each frame, its loop and that loop's confidence, the delayed loops it reports and
every candidate's matches, inliers, confidence and sequence score, floats by ``repr`` (every digit): run it with
each version of the code on the path (``PYTHONPATH=<a checkout> python bench/same_frames.py FOLDER OUT.json``: the
script imports the detector from there), then compare the two files (``cmp``). Also logs the mean and median ms a
frame.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from retrieval.detector import FrameResult, LoopDetector
from retrieval.sequences import open_sequence

__all__ = ["frame_record", "main"]

log = logging.getLogger(__name__)


def frame_record(res: FrameResult) -> dict[str, Any]:
    """One frame's result as text-exact JSON values (floats by ``repr``)."""
    return {"frame": res.frame_id,
            "loop": None if res.loop is None else [res.loop.frame_id, repr(res.loop.confidence)],
            "confirmed": [[q, c.frame_id, repr(c.confidence)] for q, c in res.confirmed],
            "candidates": [[c.frame_id, c.matches, c.inliers, repr(c.confidence), repr(float(c.seq_score))]
                           for c in res.candidates]}


def main(folder: str | Path, out: str | Path, frames: int | None = None,
         conf: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Streams ``folder`` (its first ``frames``; None: all) with the detector conf overrides ``conf`` (None: the
    default) and writes every frame's record to ``out``."""
    seq = open_sequence(Path(folder))
    n = len(seq) if frames is None else min(frames, len(seq))
    records, ms = [], []
    with LoopDetector(conf, K=seq.K) as det:
        for i in range(n):
            res = det.process(seq.read_frame(i)[0], i)
            records.append(frame_record(res))
            ms.append(res.ms["total"])
    Path(out).write_text(json.dumps(records))
    log.info("%s: %d frames, %d loops, %d delayed; %.1f ms a frame (median %.1f)", folder, n,
             sum(r["loop"] is not None for r in records), sum(len(r["confirmed"]) for r in records),
             float(np.mean(ms)) if ms else 0.0, float(np.median(ms)) if ms else 0.0)
    return records


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folder", help="a sequence folder (KITTI layout or plain images)")
    ap.add_argument("out", help="the JSON file written")
    ap.add_argument("--frames", type=int, default=None, help="the first N frames only (default: all)")
    args = ap.parse_args()
    main(args.folder, args.out, args.frames)
