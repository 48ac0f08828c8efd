"""Views of a frame for training a code of places: the same place under another light, camera and framing.

A view is a small viewpoint change (zoom-in crop, shift, small rotation: ``warp``) followed by a photometric change
(``photometric``: gain, offset and gamma, a colour cast or grey, night-like darkening, light that varies smoothly
across the frame (``shade``), blur or a low resolution brought back up, JPEG, then sensor noise, drawn as coarse as
a sensor with fewer pixels than the network would give it: the noise of a 64x32 camera brought up to 256 px spans
4-8 network pixels, and pooling does not average it away). ``cae.train`` draws two views of one frame (or of two
temporal neighbours) and pulls their codes together; the reconstruction target is the warped frame before its
photometric change.

Shapes: batches ``(B, 3, S, S)`` float in [0, 1] (the network input, any device); every draw comes from the numpy
generator passed in, so a seeded run is reproducible.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["default_views", "view_rules", "warp", "photometric"]

default_views: dict[str, Any] = {
    "crop": 0.15,  # viewpoint: zoom in by up to this fraction of the side and shift by up to half of it
    "rotate": 5.0,  # viewpoint: rotation of up to this many degrees either way
    "colour": 0.15,  # colour cast: each channel's gain drawn in 1 +- this (0: none)
    "grey": 0.3,  # probability that a view is made grey (many robot cameras are)
    "night": 0.35,  # probability of night-like darkening: 0.15-0.6 * x ** 1.2-2.4 + 0-0.05, then sensor noise
    "noise": 0.04,  # sensor noise: Gaussian sigma drawn up to this (after darkening, on every view)
    "grain": 8.0,  # the noise drawn at 1/1 to 1/grain of the network's side (log-uniform) and brought up: the
    #               noise of a sensor with fewer pixels than the network reads (a 64x32 camera: 1/4-1/8), coarser
    #               than a pixel and not averaged away by pooling; 1 = per network pixel
    "low_res": 0.35,  # probability that a view is shrunk to 16-96 px wide (aspect 1-2.5) and brought back up
    "blur": 0.3,  # probability of a Gaussian blur of 0.5-3 network pixels
    "jpeg": 0.25,  # probability of a JPEG round trip at quality 15-60
    "shade": 0.5,  # probability of light that varies across the frame: a smooth gain (0.5-1.5) and offset (+-0.25)
    #               drawn on a 2-4 cell grid and brought up (shadows, a sunlit or snow-covered ground, headlights)
}
#: allowed values of ``default_views`` (checked by ``cae.train.conf_rules``)
view_rules: dict[str, tuple[float, float]] = {"crop": (0.0, 0.5), "rotate": (0.0, 45.0), "colour": (0.0, 0.9),
                                              "grey": (0.0, 1.0), "night": (0.0, 1.0), "noise": (0.0, 0.5),
                                              "grain": (1.0, 64.0),
                                              "low_res": (0.0, 1.0), "blur": (0.0, 1.0), "jpeg": (0.0, 1.0),
                                              "shade": (0.0, 1.0)}


def _per_image(rng: np.random.Generator, lo: float, hi: float, b: int, like: torch.Tensor,
               shape: tuple[int, ...] = (1, 1, 1)) -> torch.Tensor:
    return torch.as_tensor(rng.uniform(lo, hi, (b, *shape)), dtype=like.dtype, device=like.device)


def warp(x: torch.Tensor, rng: np.random.Generator, crop: float, rotate: float) -> torch.Tensor:
    """A random zoom-in crop, shift and rotation of each image, ``(B, 3, S, S)`` -> same shape (reflected borders)."""
    b = len(x)
    if b == 0 or (crop == 0 and rotate == 0):
        return x
    scale = rng.uniform(1 - crop, 1, b)  # the part of the frame kept
    angle = np.radians(rng.uniform(-rotate, rotate, b))
    shift = rng.uniform(-1, 1, (b, 2)) * (1 - scale)[:, None]
    cos, sin = np.cos(angle) * scale, np.sin(angle) * scale
    theta = np.stack([np.stack([cos, -sin, shift[:, 0]], 1), np.stack([sin, cos, shift[:, 1]], 1)], 1)
    grid = F.affine_grid(torch.as_tensor(theta, dtype=x.dtype, device=x.device), list(x.shape), align_corners=False)
    return F.grid_sample(x, grid, mode="bilinear", padding_mode="reflection", align_corners=False)


def _gaussian_blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    radius = max(1, int(math.ceil(2.5 * sigma)))
    t = torch.arange(-radius, radius + 1, dtype=x.dtype, device=x.device)
    k = torch.exp(-0.5 * (t / sigma) ** 2)
    k = (k / k.sum()).repeat(x.shape[1], 1, 1, 1)
    pad = F.pad(x, (radius, radius, radius, radius), mode="reflect")
    out = F.conv2d(pad, k.view(-1, 1, 1, len(t)), groups=x.shape[1])
    return F.conv2d(out, k.view(-1, 1, len(t), 1), groups=x.shape[1])


def _degrade(im: torch.Tensor, rng: np.random.Generator, conf: dict[str, Any]) -> torch.Tensor:
    """One image ``(1, 3, S, S)``: blur, low resolution and JPEG, each with its probability."""
    side = im.shape[-1]
    if rng.random() < conf["blur"]:
        im = _gaussian_blur(im, float(rng.uniform(0.5, 3.0)))
    if rng.random() < conf["low_res"]:
        w = int(rng.integers(16, 97))
        h = max(8, int(round(w / rng.uniform(1.0, 2.5))))
        im = F.interpolate(F.interpolate(im, size=(h, w), mode="area"), size=(side, side), mode="bilinear",
                           align_corners=False)
    if rng.random() < conf["jpeg"]:
        u8 = (im[0].permute(1, 2, 0).clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
        ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(15, 61))])
        if ok:
            back = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).reshape(u8.shape)
            im = torch.from_numpy(back).to(im.device).permute(2, 0, 1)[None].to(im.dtype) / 255.0
    return im


def photometric(x: torch.Tensor, rng: np.random.Generator, strength: float, conf: dict[str, Any]) -> torch.Tensor:
    """A random change of light and camera per image, ``(B, 3, S, S)`` in [0, 1] -> same shape in [0, 1].

    Args:
        x: images.
        rng: the draws' generator.
        strength: gain and gamma in ``1 +- strength``, offset in ``+- strength / 2`` (``cae.train`` ``augment``).
        conf: ``default_views`` keys (colour, grey, night, shade, noise, grain, low_res, blur, jpeg).
    """
    b = len(x)
    if b == 0:
        return x
    if strength:
        gain, gamma = _per_image(rng, 1 - strength, 1 + strength, b, x), _per_image(rng, 1 - strength, 1 + strength,
                                                                                     b, x)
        x = x.clamp(1e-4, 1).pow(gamma) * gain + _per_image(rng, -strength / 2, strength / 2, b, x)
    if conf["colour"]:
        x = x * _per_image(rng, 1 - conf["colour"], 1 + conf["colour"], b, x, (3, 1, 1))
    grey = torch.as_tensor(rng.random(b) < conf["grey"], device=x.device)[:, None, None, None]
    x = torch.where(grey, x.mean(1, keepdim=True).expand_as(x), x).clamp(0, 1)
    night = torch.as_tensor(rng.random(b) < conf["night"], device=x.device)[:, None, None, None]
    dark = _per_image(rng, 0.15, 0.6, b, x) * x.clamp(1e-4, 1).pow(_per_image(rng, 1.2, 2.4, b, x)) \
        + _per_image(rng, 0.0, 0.05, b, x)
    x = torch.where(night, dark, x)
    if conf["shade"]:
        x = _shaded(x, rng, conf["shade"])
    x = torch.cat([_degrade(x[i:i + 1], rng, conf) for i in range(b)])
    sigma = _per_image(rng, 0, conf["noise"], b, x)
    return (x + sigma * _sensor_noise(rng, x, conf["grain"])).clamp(0, 1)


def _shaded(x: torch.Tensor, rng: np.random.Generator, share: float) -> torch.Tensor:
    """A share ``share`` of the images ``(B, C, S, S)`` under light that varies smoothly across the frame: each a
    gain field in 0.5-1.5 and an offset field in +-0.25, drawn on a grid of 2-4 cells a side and brought up
    bilinearly (the same field on every channel); the others unchanged. Clamped to [0, 1]."""
    b, side = x.shape[0], x.shape[-1]
    out = []
    for i in range(b):
        if rng.random() >= share:
            out.append(x[i:i + 1])
            continue
        n = int(rng.integers(2, 5))
        cells = torch.as_tensor(np.stack([rng.uniform(0.5, 1.5, (n, n)), rng.uniform(-0.25, 0.25, (n, n))]),
                                dtype=x.dtype, device=x.device)[None]
        gain, offset = F.interpolate(cells, size=(side, side), mode="bilinear", align_corners=True)[0]
        out.append((x[i:i + 1] * gain + offset).clamp(0, 1))
    return torch.cat(out) if out else x


def _sensor_noise(rng: np.random.Generator, like: torch.Tensor, grain: float) -> torch.Tensor:
    """Unit Gaussian noise shaped like ``like`` ``(B, C, S, S)``; with ``grain`` > 1, each image's drawn on a grid
    ``S / g`` on a side (``g`` log-uniform in ``[1, grain]``) and brought up bilinearly, as a sensor with fewer pixels
    than the network reads would give it (its per-pixel sigma kept: bilinear interpolation smooths it)."""
    if grain <= 1:
        return torch.as_tensor(rng.standard_normal(like.shape), dtype=like.dtype, device=like.device)
    b, c, side = like.shape[0], like.shape[1], like.shape[-1]
    parts = []
    for g in grain ** rng.random(b):
        n = max(1, int(round(side / g)))
        part = torch.as_tensor(rng.standard_normal((1, c, n, n)), dtype=like.dtype, device=like.device)
        parts.append(part if n == side else F.interpolate(part, size=(side, side), mode="bilinear",
                                                             align_corners=False))
    return torch.cat(parts) if parts else like.new_zeros(like.shape)
