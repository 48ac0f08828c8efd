"""Real frames from ``../shared``, augmented: the stream and index benchmarks' input (more frames than the data
sets hold, each a real image seen with another exposure and framing).

Each augmented frame is a real frame with a random photometric change (gain, offset and gamma, as the CAE's
training jitter) and a random crop (``crop`` of each side at most) resized back to the frame's size, so that it
keeps the real image statistics and its place while no two frames are the same pixels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from cae_lcd.core.images import image_entries, read_image

__all__ = ["shared_frames", "augment", "augmented_frames", "darken", "dusk", "narrower", "coarse"]

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "datasets"  #: the real data sets


def shared_frames(root: str | Path = SHARED, kitti_only: bool = False) -> list[Path]:
    """Image files of every data set under ``root`` (KITTI sequences, Nordland), sorted; ``kitti_only`` keeps the
    KITTI ones (all of one size, as a camera stream has)."""
    root = Path(root)
    seqs = sorted((root / "kitti" / "sequences").glob("*/image_0"))
    out = [p for s in seqs for p in image_entries(s)]
    if not kitti_only and (root / "nordland" / "images").is_dir():
        out += image_entries(root / "nordland" / "images")
    return out


def augment(image: np.ndarray, rng: np.random.Generator, strength: float = 0.3, crop: float = 0.1) -> np.ndarray:
    """One random photometric + crop augmentation of a uint8 image, same shape and dtype.

    Args:
        image: ``(H, W[, C])`` uint8.
        strength: gain and gamma drawn in ``1 +- strength``, offset in ``+- strength / 2`` (of full scale).
        crop: at most this fraction of each side is cut before resizing back.
    """
    h, w = image.shape[:2]
    t, l, b, r = (rng.uniform(0, crop, 4) * (h, w, h, w)).astype(int)
    cut = image[t:h - b, l:w - r]
    x = cv2.resize(cut, (w, h), interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
    gain, gamma = rng.uniform(1 - strength, 1 + strength, 2)
    offset = rng.uniform(-strength / 2, strength / 2)
    x = np.clip(np.power(np.clip(x, 1e-4, 1), gamma) * gain + offset, 0, 1)
    return (x * 255 + 0.5).astype(np.uint8)


def darken(image: np.ndarray, rng: np.random.Generator, scale: float = 0.35, gamma: float = 1.8,
           floor: float = 0.03, blur_sigma: float = 0.8, noise_sigma: float = 0.02) -> np.ndarray:
    """The night proxy of the decision and learned-code issues: a frame made dark, soft and noisy.

    On grey in [0, 1]: ``scale * im ** gamma + floor``, a Gaussian blur of ``blur_sigma`` px, Gaussian noise of
    ``noise_sigma``, clipped and rounded back to uint8 (a colour frame is turned grey first).

    Args:
        image: ``(H, W[, C])`` uint8.
        rng: the noise's generator (one generator seeded once per folder makes the folder reproducible).

    Returns:
        ``(H, W)`` uint8.
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    x = scale * np.power(grey.astype(np.float32) / 255.0, gamma) + floor
    x = cv2.GaussianBlur(x, (0, 0), blur_sigma)
    x = np.clip(x + rng.normal(0.0, noise_sigma, x.shape).astype(np.float32), 0, 1)
    return (x * 255 + 0.5).astype(np.uint8)


def dusk(image: np.ndarray, rng: np.random.Generator, scale: float = 0.45, gamma: float = 1.4, floor: float = 0.04,
         top: float = 1.1, bottom: float = 0.7, blur_sigma: float = 0.6, noise_sigma: float = 0.012) -> np.ndarray:
    """The day -> dusk change of the learned-code study (issue 28): less light, the ground darker than the sky.

    On grey in [0, 1]: ``scale * im ** gamma + floor``, times a vertical shading from ``top`` (first row: the sky
    keeps its light) to ``bottom`` (last row: the road loses it), a Gaussian blur of ``blur_sigma`` px, Gaussian
    noise of ``noise_sigma``, clipped and rounded back to uint8 (a colour frame is turned grey first).

    Args:
        image: ``(H, W[, C])`` uint8.
        rng: the noise's generator.

    Returns:
        ``(H, W)`` uint8.
    """
    grey = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    x = scale * np.power(grey.astype(np.float32) / 255.0, gamma) + floor
    x *= np.linspace(top, bottom, x.shape[0], dtype=np.float32)[:, None]
    x = cv2.GaussianBlur(x, (0, 0), blur_sigma)
    x = np.clip(x + rng.normal(0.0, noise_sigma, x.shape).astype(np.float32), 0, 1)
    return (x * 255 + 0.5).astype(np.uint8)


def narrower(image: np.ndarray, share: float = 0.8) -> np.ndarray:
    """A camera with a narrower lens at the same spot: the centre ``share`` of each side brought back up to the
    frame's size (OpenCV's ``INTER_AREA``), a 1 / ``share`` zoom. ``(H, W[, C])`` uint8 in and out."""
    h, w = image.shape[:2]
    ch, cw = int(round(h * share)), int(round(w * share))
    y, x = (h - ch) // 2, (w - cw) // 2
    return cv2.resize(image[y:y + ch, x:x + cw], (w, h), interpolation=cv2.INTER_AREA)


def coarse(image: np.ndarray, factor: int = 2) -> np.ndarray:
    """A camera of ``1 / factor`` the resolution: the frame shrunk by area averaging, then brought back to its size
    (bilinear). ``(H, W[, C])`` uint8 in and out."""
    h, w = image.shape[:2]
    small = cv2.resize(image, (max(1, w // factor), max(1, h // factor)), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)


def augmented_frames(paths: Sequence[Path], n: int, seed: int = 0) -> Iterator[tuple[Path, np.ndarray]]:
    """``n`` augmented frames: the real frames in order, again and again, each pass with new augmentations.

    Yields:
        ``(source path, (H, W[, C]) uint8 image)``.
    """
    rng = np.random.default_rng(seed)
    for i in range(n):
        p = paths[i % len(paths)]
        img = read_image(p)  # read again each time: no cache inflating the memory a benchmark measures
        yield p, (img if i < len(paths) else augment(img, rng))
