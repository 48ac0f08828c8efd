"""The night study's noise placements (issue 28): the noise per network pixel is fine-grained at the network's side;
the study's darkened frames carry it at their own resolution, coarse once brought up."""

import cv2
import numpy as np

from bench.augment import darken
from bench.sensor_noise import noise_per_network_pixel
from cae.model import INPUT_SIZE
from cae_lcd.core.images import read_image
from tests.conftest import NORDLAND


def neighbour_corr(noise: np.ndarray) -> float:
    n = noise - noise.mean()
    return float((n[:, 1:] * n[:, :-1]).mean() / (n * n).mean())


def test_noise_per_network_pixel_is_finer_than_the_frames_own():
    frame = read_image(sorted((NORDLAND / "images").glob("*.png"))[600])  # a winter frame, 64x32
    clean = cv2.resize(darken(frame, np.random.default_rng(0), noise_sigma=0.0), (INPUT_SIZE, INPUT_SIZE),
                       interpolation=cv2.INTER_LINEAR).astype(np.float32)
    raw = noise_per_network_pixel(frame, np.random.default_rng(0))
    fine = raw.astype(np.float32)
    coarse = cv2.resize(darken(frame, np.random.default_rng(0)), (INPUT_SIZE, INPUT_SIZE),
                        interpolation=cv2.INTER_LINEAR).astype(np.float32)
    assert raw.shape == (INPUT_SIZE, INPUT_SIZE) and raw.dtype == np.uint8
    assert 3 < (fine - clean).std() < 7  # sigma 0.02 of 255, clipping aside
    assert neighbour_corr(fine - clean) < 0.2 < 0.6 < neighbour_corr(coarse - clean)
