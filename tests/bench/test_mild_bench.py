"""bench.mild: the parts that are quick enough for a test (the comparison and the timings are benchmarks)."""

from __future__ import annotations

import numpy as np

from bench.mild import FLIP_BYTES, _database, recall_analysis
from retrieval.mild import MildDescriptor


class TestRecallAnalysis:
    def test_plot_and_table(self, tmp_path):
        table, plot = recall_analysis(tmp_path, ms=(8, 16))
        assert plot.is_file() and plot.stat().st_size > 10_000
        assert "| 16 | 16 | 0.866 |" in table  # R(16), MILD eq. 9


class TestDatabase:
    def test_real_then_noisy_copies(self, sample_image):
        real = [MildDescriptor({"max_features": 100})(sample_image(i)) for i in (0, 40)]
        index = _database(real, 5, 2.0, np.random.default_rng(0))
        assert index.n_images == 5
        start = len(real[0]) + len(real[1])
        copy = index._desc[start:start + len(real[0])]  # image 2: a noisy copy of image 0
        flipped = np.unpackbits(copy ^ real[0], axis=1).mean()
        assert abs(flipped - 0.5 ** FLIP_BYTES) < 0.02
        assert np.argmax(index.query(real[0])[:2]) == 0
