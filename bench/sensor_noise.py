"""Where a code loses at night: the darkening, or the sensor noise, and at which grain.

Nordland summer -> winter with the winter frames darkened as the training study darkens them (``bench.augment.darken``:
``0.35 * x ** 1.8 + 0.03``, blur 0.8 px, noise sigma 0.02, seed 0), in three ways: without the noise; with the noise
drawn per network pixel (the frame brought up to 256x256 first, as the training views drew it before ``grain``);
and with the noise at the frames' own 64x32 (the study's set: a 64x32 camera's noise, 4-8 network pixels a grain).
Single-frame Recall@1 / @10 (``bench.methods.single_frame_retrieval``) for the shipped weights, the
reconstruction-only weights and the thumbnail. The gap between the last two columns is what ``cae.views``' ``grain``
trains for.

``python -m bench.sensor_noise [--out runs/bench/sensor_noise] [--no-write]``
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from cae.model import INPUT_SIZE

from .common import REPO, md_table, season_frames, work_study_cli

log = logging.getLogger(__name__)


def noise_per_network_pixel(image: np.ndarray, rng: np.random.Generator, sigma: float = 0.02) -> np.ndarray:
    """``darken`` without its noise, brought up to the network's side, then Gaussian noise of ``sigma`` per pixel.

    Args:
        image: ``(H, W[, C])`` uint8.
        rng: the noise's generator.

    Returns:
        ``(256, 256)`` uint8.
    """
    from .augment import darken

    up = cv2.resize(darken(image, rng, noise_sigma=0.0), (INPUT_SIZE, INPUT_SIZE), interpolation=cv2.INTER_LINEAR)
    x = np.clip(up.astype(np.float32) / 255.0 + rng.normal(0.0, sigma, up.shape).astype(np.float32), 0, 1)
    return (x * 255 + 0.5).astype(np.uint8)


def _winter_variants() -> dict[str, Callable[[np.ndarray, np.random.Generator], np.ndarray]]:
    from .augment import darken

    return {"darkened, no noise": lambda im, rng: darken(im, rng, noise_sigma=0.0),
            "noise per network pixel (256 px)": noise_per_network_pixel,
            "noise at the frames' 64x32 (the study's set)": darken}


def main(out: str | Path, write: bool = True) -> dict[str, dict[str, str]]:
    """Measures every (code, variant) cell (``{code: {variant: "R@1 / R@10"}}``); rewrites the ``sensor_noise``
    section of BENCHMARKS.md when ``write``. ``out`` is the work folder the study CLI names (nothing is kept there:
    the frames are changed in memory)."""
    from cae.weights import RECONSTRUCTION_WEIGHTS
    from cae_lcd.core.images import read_image
    from cae_lcd.evaluation.ground_truth import read_loop_pairs
    from retrieval.descriptors import create_descriptor
    from retrieval.sequences import open_sequence

    from .methods import image_codes, single_frame_retrieval
    from .run import write_section

    nordland = REPO.parent / "shared" / "datasets" / "nordland"
    frames = [read_image(p) for p in open_sequence(nordland).frames]
    n_summer, truth = len(season_frames(nordland, "summer")), read_loop_pairs(nordland / "loops.txt")
    codes = {"shipped weights": {"name": "cae"},
             "reconstruction only (cae_mixed.pt)": {"name": "cae", "weights": str(RECONSTRUCTION_WEIGHTS)},
             "thumbnail 64x48": {"name": "thumbnail"}}
    results: dict[str, dict[str, str]] = {}
    for label, conf in codes.items():
        desc = create_descriptor(conf)
        results[label] = {}
        for variant, change in _winter_variants().items():
            rng = np.random.default_rng(0)
            images = frames[:n_summer] + [change(im, rng) for im in frames[n_summer:]]
            rk = single_frame_retrieval(image_codes(images, desc), n_summer, truth)
            results[label][variant] = f"{rk[1]:.3f} / {rk[10]:.3f}"
            log.info("%s, %s: %s", label, variant, results[label][variant])
    variants = list(_winter_variants())
    body = ("## Where a code loses at night: the noise, and its grain (`python -m bench.sensor_noise`)\n\n"
            + (__doc__ or "").split("\n\n")[1].replace("\n", " ").replace("``", "`") + "\n\n"
            + md_table(["code", *(f"winter {v}: Recall@1 / @10" for v in variants)],
                       [[label, *(row[v] for v in variants)] for label, row in results.items()]) + "\n")
    if write:
        write_section(REPO / "BENCHMARKS.md", body, "sensor_noise")
    return results


if __name__ == "__main__":
    work_study_cli(main, __doc__, "runs/bench/sensor_noise")
