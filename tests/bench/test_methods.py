"""The training study's single-frame measure (issue 28) against a brute-force count, the dusk pass and the coarse
camera."""

import numpy as np

import cv2

from bench.augment import coarse, dusk
from bench.methods import single_frame_retrieval


def codes_with_revisits(n_places=40, seed=0):
    """``2 * n_places`` codes: places 0..n-1, then each revisited (a noisy copy), in order."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(n_places, 64))
    return np.concatenate([base, base + 0.3 * rng.normal(size=base.shape)]).astype(np.float32)


def test_revisits_found_and_window_respected():
    x = codes_with_revisits()
    truth = np.array([(40 + i, i) for i in range(40)])
    assert single_frame_retrieval(x, 40, truth, exclude_recent=10) == {1: 1.0, 10: 1.0}
    # a query searches only frames at least exclude_recent older: 40 apart, a window of 41 leaves no true frame
    assert np.isnan(single_frame_retrieval(x, 40, truth, exclude_recent=41)[1])
    wrong = np.array([(40 + i, (i + 7) % 40) for i in range(40)])  # a truth that does not hold
    assert single_frame_retrieval(x, 40, wrong, exclude_recent=10)[1] < 0.1


def test_no_query_with_a_pair_is_nan():
    x = codes_with_revisits()
    r = single_frame_retrieval(x, 40, np.array([(5, 1)]), exclude_recent=2)
    assert np.isnan(r[1]) and np.isnan(r[10])


def test_dusk_darkens_the_ground_more_than_the_sky(sample_image):
    image = sample_image(0)
    out = dusk(image, np.random.default_rng(0))
    grey = image if image.ndim == 2 else image.mean(2)
    assert out.shape == grey.shape[:2] and out.dtype == np.uint8
    h = out.shape[0] // 4
    ratio_top = out[:h].mean() / grey[:h].mean()
    ratio_bottom = out[-h:].mean() / grey[-h:].mean()
    assert ratio_bottom < ratio_top < 1


def test_coarse_keeps_the_size_and_loses_the_fine_detail(sample_image):
    image = sample_image(0)
    out = coarse(image)
    assert out.shape == image.shape and out.dtype == np.uint8
    detail = lambda im: cv2.Laplacian(im.astype(np.float32), cv2.CV_32F).var()
    assert detail(out) < 0.5 * detail(image)
    assert abs(float(out.mean()) - float(image.mean())) < 1.0  # the light stays
    np.testing.assert_array_equal(coarse(image, 1), image)
