"""From what OpenCV reads to what the network and the feature extractors take.

Accepted images (numpy arrays, as ``cv2.imread(path, cv2.IMREAD_UNCHANGED)`` returns them):
grey ``(H, W)``, grey ``(H, W, 1)``, BGR ``(H, W, 3)``, BGRA ``(H, W, 4)``; dtype uint8, uint16 (any bit depth up
to 16: 10-, 12- and 14-bit data stored in 16-bit words are scaled by their own range) or float in [0, 1]; any size
(small images such as 160x120 are upsampled).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch

from .model import INPUT_SIZE

__all__ = ["IMAGE_EXTENSIONS", "ImageError", "read_image", "to_uint8", "to_gray_u8", "to_rgb_u8", "resize_square", "to_network_u8", "network_tensor", "preprocess"]

log = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")


class ImageError(ValueError):
    """An image could not be read or has a layout we cannot interpret."""


def read_image(path: str | Path) -> np.ndarray:
    """Reads an image file unchanged (grey or colour, 8- or 16-bit).

    Raises:
        ImageError: the file is missing, unreadable or corrupt.
    """
    data = np.fromfile(str(path), dtype=np.uint8) if Path(path).is_file() else None
    if data is None or data.size == 0:
        raise ImageError(f"cannot read image {path}: missing or empty file")
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise ImageError(f"cannot decode image {path}: corrupt or unsupported format")
    return img


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Converts any accepted dtype to uint8, keeping the channel layout.

    uint16 images are scaled by their bit depth, inferred from the maximum value (a 12-bit image with max 4095 maps
    to 255), so 10/12/14-bit sensors look like 8-bit ones. Floats are taken to be in [0, 1].
    """
    if image.dtype == np.uint8:
        return image
    if image.dtype == np.uint16:
        top = int(image.max()) if image.size else 0
        bits = max(8, int(np.ceil(np.log2(top + 1)))) if top > 0 else 8
        return cv2.convertScaleAbs(image, alpha=255.0 / (2**bits - 1))
    if np.issubdtype(image.dtype, np.floating):
        return np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    raise ImageError(f"unsupported image dtype {image.dtype}; expected uint8, uint16 or float")


def _check_layout(image: np.ndarray) -> None:
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise ImageError(f"unsupported image shape {image.shape}; expected (H, W), (H, W, 1), (H, W, 3) or (H, W, 4)")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise ImageError(f"image too small: {image.shape[1]}x{image.shape[0]} pixels (need at least 8x8)")


def to_gray_u8(image: np.ndarray) -> np.ndarray:
    """Any accepted image -> grey uint8 ``(H, W)``."""
    _check_layout(image)
    img = to_uint8(image)
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return np.ascontiguousarray(img)


def to_rgb_u8(image: np.ndarray) -> np.ndarray:
    """Any accepted image -> RGB uint8 ``(H, W, 3)``; grey is replicated to three channels."""
    _check_layout(image)
    img = to_uint8(image)
    if img.ndim == 2 or img.shape[2] == 1:
        return cv2.cvtColor(img.reshape(img.shape[:2]), cv2.COLOR_GRAY2RGB)
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)


def resize_square(image: np.ndarray, size: int = INPUT_SIZE) -> np.ndarray:
    """Resizes to ``size x size`` (aspect not kept, as in the paper): area averaging down, bilinear up."""
    h, w = image.shape[:2]
    interp = cv2.INTER_AREA if (h >= size and w >= size) else cv2.INTER_LINEAR
    return cv2.resize(image, (size, size), interpolation=interp)


def to_network_u8(image: np.ndarray, size: int = INPUT_SIZE) -> np.ndarray:
    """Any accepted image -> the network's image before scaling, ``(size, size, 3)`` uint8 RGB.

    Resizes first (one channel for grey input), then expands to RGB: cheaper than the other way round.
    """
    _check_layout(image)
    return to_rgb_u8(resize_square(to_uint8(image), size))


def preprocess(images: np.ndarray | Sequence[np.ndarray], size: int = INPUT_SIZE) -> torch.Tensor:
    """Images as OpenCV reads them -> the network input.

    Args:
        images: one image or a sequence of images (each grey/BGR/BGRA, uint8/uint16/float, any size).
        size: network input side.

    Returns:
        ``(B, 3, size, size)`` float32 in [0, 1], RGB, channels-last memory layout; ``B = 0`` for an empty list.
    """
    if isinstance(images, np.ndarray):
        images = [images]
    if len(images) == 0:
        return torch.empty((0, 3, size, size), dtype=torch.float32).contiguous(memory_format=torch.channels_last)
    return network_tensor(np.stack([to_network_u8(img, size) for img in images]))


def network_tensor(batch: np.ndarray) -> torch.Tensor:
    """``(B, S, S, 3)`` uint8 RGB (``to_network_u8`` output) -> ``(B, 3, S, S)`` float32 in [0, 1], channels-last."""
    # (B, S, S, 3) -> (B, 3, S, S) view whose memory is already channels-last: no copy before the cast.
    x = torch.from_numpy(np.ascontiguousarray(batch)).permute(0, 3, 1, 2)
    return x.to(torch.float32).div_(255.0)
