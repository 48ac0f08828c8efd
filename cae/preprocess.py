"""From what OpenCV reads to what the network takes: ``(B, 3, 256, 256)`` float in [0, 1], RGB, channels-last.

Image reading and dtype/layout conversion are the base layer's (``cae_lcd.core.images``); this module only adds the
network's resize, the low-pass some weights read their small images through (``lowpass``) and the tensor layout.
"""

from __future__ import annotations

from typing import Sequence

import cv2
import numpy as np
import torch

from cae_lcd.core.images import check_image, resize_square, to_rgb_u8, to_uint8

from .model import INPUT_SIZE

__all__ = ["to_network_u8", "network_tensor", "preprocess", "MAX_LOWPASS"]

MAX_LOWPASS = 3.0  #: the largest ``lowpass`` sigma a conf or a checkpoint may give, in the image's own pixels


def to_network_u8(image: np.ndarray, size: int = INPUT_SIZE, lowpass: float = 0.0) -> np.ndarray:
    """Any accepted image -> the network's image before scaling, ``(size, size, 3)`` uint8 RGB.

    Resizes first (one channel for grey input), then expands to RGB: cheaper than the other way round.

    Args:
        image: grey/BGR/BGRA, uint8/uint16/float, any size.
        size: network input side.
        lowpass: Gaussian sigma, in the image's own pixels, applied before an image smaller than ``size`` on both
            sides is brought up (a 64x32 frame 4-8x: its pixel grid would be drawn as ridges, its noise as blobs);
            0 = none. The weights' own (``Encoder.lowpass``, from the checkpoint's conf): codes are comparable only
            under the value the weights were trained with.
    """
    image = to_uint8(check_image(image))
    if lowpass > 0 and max(image.shape[:2]) < size:
        image = cv2.GaussianBlur(image, (0, 0), lowpass)
    return to_rgb_u8(resize_square(image, size))


def preprocess(images: np.ndarray | Sequence[np.ndarray], size: int = INPUT_SIZE, lowpass: float = 0.0
               ) -> torch.Tensor:
    """Images as OpenCV reads them -> the network input.

    Args:
        images: one image or a sequence of images (each grey/BGR/BGRA, uint8/uint16/float, any size).
        size: network input side.
        lowpass: see ``to_network_u8``.

    Returns:
        ``(B, 3, size, size)`` float32 in [0, 1], RGB, channels-last memory layout; ``B = 0`` for an empty list.

    Raises:
        ImageError: an image is not an array of an accepted layout (the message says which one).
    """
    if isinstance(images, np.ndarray):
        images = [images]
    if len(images) == 0:
        return torch.empty((0, 3, size, size), dtype=torch.float32).contiguous(memory_format=torch.channels_last)
    return network_tensor(np.stack([to_network_u8(img, size, lowpass) for img in images]))


def network_tensor(batch: np.ndarray) -> torch.Tensor:
    """``(B, S, S, 3)`` uint8 RGB (``to_network_u8`` output) -> ``(B, 3, S, S)`` float32 in [0, 1], channels-last."""
    # (B, S, S, 3) -> (B, 3, S, S) view whose memory is already channels-last: no copy before the cast.
    x = torch.from_numpy(np.ascontiguousarray(batch)).permute(0, 3, 1, 2)
    return x.to(torch.float32).div_(255.0)
