"""Side-by-side speed choices of the per-frame path, measured in one run on the same frames.

``python -m bench.speed_ablation [--sequence ../shared/datasets/kitti/sequences/90]`` prints a Markdown table:
the default detector against one change at a time (no feature worker thread, geometric check on every
candidate), and the descriptor-matching GEMM in numpy/OpenBLAS against torch (what the detector uses).
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np

from cae_lcd.core.images import read_image
from retrieval.detector import LoopDetector
from retrieval.sequences import open_sequence
from verify.features import SIFT
from verify.matching import match_ratio, match_ratio_many

VARIANTS = {
    "default (feature worker thread, 1 thread a library, branch and bound)": {},
    "no feature worker (features on the main thread)": {"runtime": {"feature_worker": False}},
    "geometric check on every candidate": {"policy": {"check_all": True}},
    "no F pre-check before E": {"geometry": {"prefilter": False}},
}


def detector_variants(images: list[np.ndarray], K: np.ndarray, skip: int = 50) -> list[tuple[str, float, float, int]]:
    """``(name, median ms, p90 ms, loops)`` per variant, each over the same frames (the first ``skip`` frames,
    which have no candidates yet, are left out of the statistics)."""
    rows = []
    for name, conf in VARIANTS.items():
        with LoopDetector(conf, K=K) as det:
            results = [det.process(img, i) for i, img in enumerate(images)]
        total = [r.ms["total"] for r in results[skip:]]
        rows.append((name, float(np.median(total)), float(np.percentile(total, 90)),
                     sum(r.loop is not None for r in results)))
    return rows


def matching_gemm(images: list[np.ndarray], repeats: int = 20) -> tuple[float, float]:
    """Median ms to match one frame against 10 candidates: numpy (OpenBLAS) reference vs the torch fast path."""
    feats = [SIFT().extract(img) for img in images[:11]]
    q, cands = feats[-1].descriptors, [f.descriptors for f in feats[:10]]

    def timed(fn) -> float:
        fn()
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts) * 1e3)

    return timed(lambda: [match_ratio(q, c) for c in cands]), timed(lambda: match_ratio_many(q, cands))


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    ap = argparse.ArgumentParser(prog="python -m bench.speed_ablation", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=Path("../shared/datasets/kitti/sequences/90"))
    args = ap.parse_args()
    seq = open_sequence(args.sequence)
    images = [read_image(f) for f in seq.frames]
    print("| variant | median ms/frame | p90 ms/frame | loops |\n|---|---|---|---|")
    base = None
    for name, med, p90, loops in detector_variants(images, seq.K):
        base = base or med
        print(f"| {name} | {med:.1f} ({med / base:.2f}x) | {p90:.1f} | {loops} |")
    numpy_ms, torch_ms = matching_gemm(images)
    print(f"\nMatching one frame against 10 candidates (500 SIFT each): numpy/OpenBLAS {numpy_ms:.1f} ms, "
          f"torch {torch_ms:.1f} ms ({numpy_ms / torch_ms:.1f}x)")
