"""Images -> L2-normalised codes, numpy in and numpy out."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from cae_lcd.core.errors import ConfigError, ImageError

from .model import CODE_DIM, INPUT_SIZE, Encoder
from .preprocess import network_tensor, preprocess

__all__ = ["CPU_BATCH", "encode_images", "normalize_codes"]

#: Images a forward pass on the CPU: the first layer's output is 8 MB an image (32 x 256 x 256 float32), and batches
#: that spill the last-level cache run about 3x slower an image (one core: 3.1 ms an image in batches of 1-2, 9.2 in
#: batches of 8, 11.4 in batches of 32; the codes are the same bit for bit).
CPU_BATCH = 2
GPU_BATCH = 32  #: images a forward pass on a GPU


def normalize_codes(codes: np.ndarray) -> np.ndarray:
    """Row-wise L2 normalisation, ``(B, D)`` -> ``(B, D)`` float32 (all-zero rows stay zero)."""
    codes = np.asarray(codes, dtype=np.float32)
    norms = np.linalg.norm(codes, axis=1, keepdims=True)
    return codes / np.maximum(norms, 1e-12)


def _prepared(chunk: Sequence[np.ndarray]) -> np.ndarray:
    """``(B, 256, 256, 3)`` uint8 of images said to be ``to_network_u8`` output; ImageError when one is not."""
    want = (INPUT_SIZE, INPUT_SIZE, 3)
    for i, im in enumerate(chunk):
        if not isinstance(im, np.ndarray) or im.shape != want or im.dtype != np.uint8:
            got = f"{im.dtype} {im.shape}" if isinstance(im, np.ndarray) else type(im).__name__
            raise ImageError(f"prepared image {i} must be uint8 {want} (cae.preprocess.to_network_u8); got {got}")
    return np.stack(chunk)


@torch.inference_mode()
def encode_images(encoder: Encoder, images: Sequence[np.ndarray] | np.ndarray, batch_size: int | None = None,
                  half: bool = False, prepared: bool = False) -> np.ndarray:
    """Encodes images as OpenCV reads them.

    Args:
        encoder: from ``cae.load_encoder``.
        images: a sequence of images, or one image (grey/BGR, 8/16-bit, any size).
        batch_size: images per forward pass; None: ``CPU_BATCH`` on the CPU, ``GPU_BATCH`` on a GPU.
        half: run in float16 (CUDA only; ignored on CPU, where it is slower).
        prepared: the images are already ``cae.preprocess.to_network_u8`` output (256x256x3 uint8 RGB).

    Returns:
        ``(B, 4096)`` float32, each row of unit L2 norm; ``(0, 4096)`` for no images.

    Raises:
        ConfigError: ``batch_size`` is neither None nor an integer >= 1.
        ImageError: an image is not an array of an accepted layout.
    """
    if batch_size is not None and (isinstance(batch_size, bool) or not isinstance(batch_size, (int, np.integer))
                                   or batch_size < 1):
        raise ConfigError(f"batch_size must be an integer >= 1 or None; got {batch_size!r}")
    if isinstance(images, np.ndarray):
        images = [images]
    elif not isinstance(images, (list, tuple)):
        raise ImageError(f"images must be a numpy array or a list of them; got {type(images).__name__}")
    device = next(encoder.parameters()).device
    batch_size = batch_size or (CPU_BATCH if device.type == "cpu" else GPU_BATCH)
    use_half = half and device.type == "cuda"
    out = [np.empty((0, CODE_DIM), np.float32)]
    for start in range(0, len(images), batch_size):
        chunk = images[start:start + batch_size]
        x = (network_tensor(_prepared(chunk)) if prepared else preprocess(chunk, lowpass=encoder.lowpass)).to(device)
        if use_half:
            with torch.autocast("cuda", dtype=torch.float16):
                codes = encoder(x)
        else:
            codes = encoder(x)
        out.append(codes.float().cpu().numpy())
    return normalize_codes(np.concatenate(out))
