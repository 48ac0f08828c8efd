"""Does training help the retrieval stage? How far apart the codes keep true and false matches.

On KITTI 90 every second-pass query has a true loop among the first-pass frames. For each query and each set of
weights: the cosine of its best true match, the cosine of its best false frame (>= 50 frames back, not a true
pair), their margin, and the rank of the first true match among all eligible frames (Recall@1 over the whole
map, not only the top-10). A larger margin is a retrieval stage that is harder to fool.

``python -m bench.retrieval_margin [--sequence ../shared/datasets/kitti/sequences/90]
[--other runs/bench/training/train_other/best.pt]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

import cae
from cae.model import Encoder
from cae_lcd.core.images import read_image
from retrieval.sequences import open_sequence

from .common import ground_truth_pairs


def margins(codes: np.ndarray, loops: np.ndarray, min_gap: int = 50) -> dict[str, float]:
    """``codes (N, D)`` unit-norm, ``loops (P, 2)`` true pairs -> mean true/false best cosine, margin, Recall@1."""
    sims = codes @ codes.T
    true = {(int(i), int(j)) for i, j in loops}
    rows = []
    for q in np.unique(loops[:, 0]):
        eligible = np.arange(0, q - min_gap + 1)
        is_true = np.array([(int(q), int(j)) in true for j in eligible])
        s = sims[q, eligible]
        rows.append((s[is_true].max(), s[~is_true].max(), eligible[np.argmax(s)] in eligible[is_true]))
    r = np.array(rows, dtype=np.float64)
    return {"true": r[:, 0].mean(), "false": r[:, 1].mean(), "margin": (r[:, 0] - r[:, 1]).mean(),
            "min_margin": (r[:, 0] - r[:, 1]).min(), "recall_at_1": r[:, 2].mean()}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(prog="python -m bench.retrieval_margin", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sequence", type=Path, default=Path("../shared/datasets/kitti/sequences/90"))
    ap.add_argument("--other", type=Path, default=Path("runs/bench/training/train_other/best.pt"),
                    help="weights trained on other images (cae-lcd bench --training-study writes them)")
    args = ap.parse_args()
    seq = open_sequence(args.sequence)
    loops = ground_truth_pairs(args.sequence)
    if loops is None or not len(loops):
        ap.error(f"{args.sequence}: no ground-truth loops (loops.txt); pick a sequence with revisits")
    images = [read_image(f) for f in seq.frames]
    torch.manual_seed(0)
    encoders = {"shipped (KITTI 00+07, 20 epochs)": cae.load_encoder(),
                "random init (seed 0)": Encoder().eval().to(memory_format=torch.channels_last)}
    if args.other.is_file():
        encoders["trained on 07 only (5 epochs)"] = cae.load_encoder(args.other)
    print("| weights | mean cosine, best true match | mean cosine, best false frame | mean margin | "
          "smallest margin | Recall@1 over the whole map |\n|---|---|---|---|---|---|")
    for name, enc in encoders.items():
        m = margins(cae.encode_images(enc, images), loops)
        print(f"| {name} | {m['true']:.4f} | {m['false']:.4f} | {m['margin']:.4f} | {m['min_margin']:.4f} | "
              f"{m['recall_at_1']:.3f} |")
