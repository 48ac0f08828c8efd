import cv2
import numpy as np
import pytest

from cae.encode import CPU_BATCH, encode_images, normalize_codes
from cae_lcd.core.errors import ImageError


@pytest.fixture(scope="module")
def codes(encoder, sample_image):
    """Codes of sample frames 10, 11 (neighbours) and 40 (far along the road)."""
    return encode_images(encoder, [sample_image(i) for i in (10, 11, 40)])


class TestEncodeImages:
    def test_shape_and_unit_norm(self, codes):
        assert codes.shape == (3, 4096)
        assert codes.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(codes, axis=1), 1.0, atol=1e-5)

    def test_neighbour_more_similar_than_far_frame(self, codes):
        # measured with the shipped weights: sim(10, 11) ~ 0.93, sim(10, 40) ~ 0.80
        near = float(codes[0] @ codes[1])
        far = float(codes[0] @ codes[2])
        assert near > far + 0.04
        assert near > float(codes[1] @ codes[2])

    def test_single_array_and_batching(self, encoder, sample_image, codes):
        one = encode_images(encoder, sample_image(10))
        assert one.shape == (1, 4096)
        np.testing.assert_allclose(one[0], codes[0], atol=1e-5)
        small_batches = encode_images(encoder, [sample_image(i) for i in (10, 11, 40)], batch_size=2)
        np.testing.assert_allclose(small_batches, codes, atol=1e-5)

    def test_the_cpu_runs_cache_sized_batches_with_the_same_codes(self, encoder, sample_image, monkeypatch):
        """On the CPU the forward passes take at most ``CPU_BATCH`` images (larger batches spill the cache: 3x slower
        an image), and the codes are those of one pass over all of them, bit for bit."""
        images = [sample_image(i) for i in range(5)]
        whole = encode_images(encoder, images, batch_size=32)
        sizes: list[int] = []
        hook = encoder.register_forward_pre_hook(lambda _, args: sizes.append(args[0].shape[0]))
        try:
            default = encode_images(encoder, images)
        finally:
            hook.remove()
        assert 1 <= CPU_BATCH <= 3 and max(sizes) == CPU_BATCH and sum(sizes) == 5  # 8 MB of activations an image
        assert np.array_equal(default, whole)

    def test_formats_give_same_code(self, encoder, sample_image, codes):
        g = sample_image(10)
        imgs = [cv2.cvtColor(g, cv2.COLOR_GRAY2BGR), g.astype(np.uint16) * 257, g.astype(np.float32) / 255.0]
        np.testing.assert_allclose(encode_images(encoder, imgs), np.repeat(codes[:1], 3, axis=0), atol=1e-5)

    @pytest.mark.parametrize("bad", ["grey", "small", "float"])
    def test_prepared_images_of_another_layout_are_refused_with_one_line(self, encoder, sample_image, bad):
        image = {"grey": sample_image(0), "small": np.zeros((64, 64, 3), np.uint8),
                 "float": np.zeros((256, 256, 3), np.float32)}[bad]
        with pytest.raises(ImageError, match="prepared image 0 must be uint8"):
            encode_images(encoder, [image], prepared=True)

    def test_empty(self, encoder):
        out = encode_images(encoder, [])
        assert out.shape == (0, 4096)
        assert out.dtype == np.float32


class TestNormalizeCodes:
    def test_rows_unit_and_zero_rows_stay_zero(self):
        x = np.array([[3.0, 4.0], [0.0, 0.0], [-1.0, 0.0]])
        out = normalize_codes(x)
        np.testing.assert_allclose(out, [[0.6, 0.8], [0.0, 0.0], [-1.0, 0.0]], atol=1e-7)
        assert out.dtype == np.float32
        assert np.isfinite(out).all()
