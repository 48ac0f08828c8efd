"""cae.whitening: fit, transform, and the round trip through a saved checkpoint."""

from __future__ import annotations

import numpy as np
import pytest

from cae.encode import encode_images
from cae.weights import load_encoder, save_checkpoint
from cae.whitening import Whitening
from cae_lcd.core.conf import ConfigError


@pytest.fixture(scope="module")
def sample_codes(encoder, sample_frames):
    from cae_lcd.core.images import read_image
    return encode_images(encoder, [read_image(p) for p in sample_frames[:40]])


class TestWhiteningFit:
    def test_whitened_codes_are_decorrelated_unit_vectors(self, sample_codes):
        w = Whitening.fit(sample_codes, dim=10, shrink=0.0)
        y = w.transform(sample_codes)
        assert y.shape == (40, 10) and np.allclose(np.linalg.norm(y, axis=1), 1, atol=1e-5)
        raw = sample_codes @ sample_codes.T
        white = y @ y.T
        off = ~np.eye(40, dtype=bool)
        assert white[off].mean() < 0.05 < raw[off].mean()  # raw codes of one camera all look alike

    def test_dim_capped_by_samples(self, sample_codes):
        assert Whitening.fit(sample_codes[:40], dim=256).dim == 10

    def test_deterministic(self, sample_codes):
        a, b = Whitening.fit(sample_codes), Whitening.fit(sample_codes.copy())
        assert a.identity() == b.identity()

    def test_refuses_too_few_or_nan(self, sample_codes):
        with pytest.raises(ConfigError, match="at least"):
            Whitening.fit(sample_codes[:3])
        bad = sample_codes.copy()
        bad[0, 0] = np.nan
        with pytest.raises(ConfigError, match="NaN"):
            Whitening.fit(bad)

    def test_principal_directions_from_the_gram_matrix_are_the_svds(self, sample_codes):
        """Fewer codes than dimensions (a stream's fit): the leading singular values and directions from the codes'
        Gram matrix (the fast path) against the SVD of the codes themselves (brute force), up to each direction's
        sign; and the SVD itself where codes outnumber dimensions."""
        from cae.whitening import _principal

        x = sample_codes.astype(np.float64) - sample_codes.mean(0)
        _, s, vt = np.linalg.svd(x, full_matrices=False)
        got_s, got_vt = _principal(x, 10)
        np.testing.assert_allclose(got_s, s[:10], rtol=1e-9)
        signs = np.sign(np.sum(got_vt * vt[:10], axis=1))
        np.testing.assert_allclose(got_vt, vt[:10] * signs[:, None], atol=1e-9)
        tall = x[:, :20]
        np.testing.assert_allclose(_principal(tall, 5)[0], np.linalg.svd(tall, compute_uv=False)[:5], rtol=1e-12)

    def test_empty_transform(self, sample_codes):
        assert Whitening.fit(sample_codes).transform(np.zeros((0, 4096))).shape[0] == 0


class TestWhiteningCheckpoint:
    def test_round_trip(self, tmp_path, encoder, sample_codes):
        w = Whitening.fit(sample_codes, dim=32)
        save_checkpoint(tmp_path / "w.pt", encoder, {}, whitening=w)
        loaded = load_encoder(tmp_path / "w.pt", "cpu")
        assert loaded.whitening is not None and loaded.whitening.identity() == w.identity()
        np.testing.assert_allclose(loaded.whitening.transform(sample_codes), w.transform(sample_codes), atol=1e-6)

    def test_weights_without_whitening(self, encoder):
        assert getattr(encoder, "whitening", None) is None  # the shipped weights carry none

    def test_damaged_state_refused(self):
        with pytest.raises(ConfigError, match="damaged"):
            Whitening.from_state({"mean": np.zeros(4), "projection": np.zeros((2, 5)), "variance": np.ones(2),
                                  "fitted_on": 3})
