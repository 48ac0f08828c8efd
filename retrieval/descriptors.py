"""Global image descriptors that the index searches: the CAE code by default; baselines plug in by name.

A descriptor maps one image (and, when ``needs_features``, its local features) to a unit-norm ``(dim,)`` float32
vector whose inner products are similarities. ``identity`` names the weights or vocabulary, so a keyframe database
is never resumed with a different descriptor.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from cae_lcd.core.conf import Bool, Registry, Text, configure
from cae.encode import encode_images
from cae.preprocess import to_network_u8
from cae.model import CODE_DIM
from cae.weights import DEVICE_PATTERN, STILL_COS, load_encoder
from verify.features import Features

__all__ = ["GlobalDescriptor", "CAEDescriptor", "DESCRIPTORS", "create_descriptor"]


class GlobalDescriptor:
    """Base class: set ``default_conf``, ``dim``, ``needs_features`` and implement ``__call__``."""

    default_conf: dict[str, Any] = {"name": ""}
    conf_rules: dict[str, Any] = {}
    needs_features = False  #: True when ``__call__`` uses the frame's local features
    searched_by = "cosine"  #: the place memory that stores and searches it (``retrieval.places.PLACES``)
    encodes_in_batches = False  #: True when ``encode_batch`` gives, bit for bit, what ``__call__`` gives

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "descriptor")
        self.dim = 0
        self.identity = ""
        self.whitening = None  #: a ``cae.whitening.Whitening`` that came with the weights, if any
        self.still_cos = STILL_COS  #: cosine of two codes at or above which the camera stood still
        self.lowpass = 0.0  #: the Gaussian sigma small images are read through (``cae.preprocess``; CAE: the weights')

    def network_image(self, image: np.ndarray) -> np.ndarray:
        """The frame as the network reads it, ``(256, 256, 3)`` uint8 RGB (``cae.preprocess.to_network_u8`` with
        this descriptor's ``lowpass``): what ``__call__``'s ``network_image`` takes."""
        return to_network_u8(image, lowpass=self.lowpass)

    def size_text(self) -> str:
        """What one frame's description holds, for tables (``"4096"``; MILD: ``"800 x 256 bits"``)."""
        return str(self.dim)

    def __call__(self, image: np.ndarray, features: Features | None = None,
                 network_image: np.ndarray | None = None) -> np.ndarray:
        """One frame -> ``(dim,)`` float32 unit-norm vector.

        Args:
            image: the frame as given (any accepted layout).
            features: its local features (passed when ``needs_features``).
            network_image: the same frame already resized for the network, ``(256, 256, 3)`` uint8 RGB
                (``cae.preprocess.to_network_u8``), when the caller has it: saves a second resize.
        """
        raise NotImplementedError

    def encode_batch(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """Several frames at once -> one ``(dim,)`` float32 code each, identical to ``__call__`` on each
        (only where ``encodes_in_batches``)."""
        raise NotImplementedError(f"{type(self).__name__} does not encode in batches")


DESCRIPTORS: Registry[GlobalDescriptor] = Registry("global descriptor")


@DESCRIPTORS.register("cae")
class CAEDescriptor(GlobalDescriptor):
    """The convolutional autoencoder's 4096-d code (Leonardi & Stahl)."""

    default_conf: dict[str, Any] = {
        "name": "cae",  # global descriptor, by registry name
        "weights": None,  # checkpoint path; None = the weights shipped in the package
        "device": "cpu",  # "cpu", "cuda", "auto"; batch-1 encoding of this small net is fastest on the CPU
        "half": False,  # float16 inference (CUDA only)
    }
    conf_rules: dict[str, Any] = {"weights": Text(optional=True), "device": Text(DEVICE_PATTERN), "half": Bool()}

    def __init__(self, conf: dict[str, Any] | None = None, encoder: torch.nn.Module | None = None) -> None:
        super().__init__(conf)
        self.encoder = encoder if encoder is not None else load_encoder(self.conf["weights"], self.conf["device"])
        self.dim = CODE_DIM
        self.identity = getattr(self.encoder, "identity", "")
        self.whitening = getattr(self.encoder, "whitening", None)
        self.still_cos = getattr(self.encoder, "still_cos", STILL_COS)  # the weights' own
        self.lowpass = getattr(self.encoder, "lowpass", 0.0)  # the weights' own

    def __call__(self, image: np.ndarray, features: Features | None = None,
                 network_image: np.ndarray | None = None) -> np.ndarray:
        if network_image is not None:
            return encode_images(self.encoder, [network_image], half=self.conf["half"], prepared=True)[0]
        return encode_images(self.encoder, [image], half=self.conf["half"])[0]

    encodes_in_batches = True

    def encode_batch(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """Batched forward passes on the network images ``LoopDetector.process`` would make (same codes, bit for
        bit: checked in the tests)."""
        nets = [self.network_image(image) for image in images]  # to_network_u8 brings any dtype to uint8
        return list(encode_images(self.encoder, nets, half=self.conf["half"], prepared=True))


def create_descriptor(conf: dict[str, Any] | None = None, **kwargs: Any) -> GlobalDescriptor:
    """The descriptor named by ``conf["name"]`` (default ``"cae"``)."""
    return DESCRIPTORS.get((conf or {}).get("name", "cae"))(conf, **kwargs)
