"""The similarity plot's ground-truth panel: each true pair marked once, on the side of the diagonal where the
detections are drawn (query down, earlier frame across); it was filled on both sides."""

from __future__ import annotations

import numpy as np

from cae_lcd.evaluation.plots import ground_truth_panel, plot_similarity


def test_one_side_of_the_diagonal(sample_dir):
    pairs = np.loadtxt(sample_dir / "loops.txt", dtype=np.int64, ndmin=2)[:, :2]
    panel = ground_truth_panel(pairs, 100)
    assert panel.sum() == len({(max(a, b), min(a, b)) for a, b in pairs.tolist()}) > 0
    assert not np.triu(panel, 1).any()
    q, e = np.maximum(pairs[:, 0], pairs[:, 1]), np.minimum(pairs[:, 0], pairs[:, 1])
    assert panel[q, e].all()
    blocks = ground_truth_panel(pairs, 34, step=3)  # subsampled: a block marked when any pair falls in it
    assert blocks[q // 3, e // 3].all() and not np.triu(blocks, 1).any()


def test_plot_writes_a_png(tmp_path, sample_dir):
    pairs = np.loadtxt(sample_dir / "loops.txt", dtype=np.int64, ndmin=2)[:, :2]
    codes = np.random.default_rng(0).normal(size=(100, 8))
    out = plot_similarity(codes, np.arange(100), 100, pairs, tmp_path / "s.png", detections=pairs[:5])
    assert out.stat().st_size > 1000
