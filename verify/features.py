"""Local features, computed once per keyframe and kept (SIFT now; other extractors plug in by name).

``Features`` is the contract between extraction, storage and matching:

    keypoints    (N, 2) float32   x, y in pixels of the ORIGINAL image (whatever scale extraction ran at)
    descriptors  (N, D) float32 for SIFT (D = 128; uint8 once ``compact``), packed uint8 for binary descriptors
    scales       (N,)   float32   keypoint diameter in original-image pixels
    metric       str              how descriptors compare: "l2" (SIFT) or "hamming" (binary); set by the extractor,
                                  never guessed from the dtype
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from cae_lcd.core.conf import Bool, ConfigError, Float, Int, Registry, configure
from cae_lcd.core.images import to_gray_u8

__all__ = ["KEYPOINT_STEP", "Features", "FeatureExtractor", "SIFT", "ORB", "FEATURES", "METRICS", "create_extractor"]

METRICS = ("l2", "hamming")  #: descriptor distances the matchers know
KEYPOINT_STEP = 8  #: keypoints are kept in 1/8 pixel (``Features.compact``): uint16 on disk, images up to 8191 px


@dataclass
class Features:
    keypoints: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray
    metric: str = "l2"  #: "l2" or "hamming": a property of the extractor, kept through storage

    def __post_init__(self) -> None:
        if self.metric not in METRICS:
            raise ConfigError(f"unknown descriptor metric {self.metric!r}; expected one of {', '.join(METRICS)}")

    def __len__(self) -> int:
        return len(self.keypoints)

    def compact(self) -> "Features":
        """The features as the keyframe store keeps them: float descriptors as uint8 when that is exact (SIFT's are
        integers in 0..255: 4x less memory and disk, same matches; others unchanged), keypoints rounded to
        1/``KEYPOINT_STEP`` pixel and scales to float16 precision (what a resumed run reads back, so a resumed and
        an uninterrupted run verify with the same numbers). Idempotent."""
        d = self.descriptors
        if d.dtype != np.uint8 and d.size and d.min() >= 0 and d.max() <= 255 and np.array_equal(d, np.round(d)):
            d = d.astype(np.uint8)
        kp = np.clip(np.round(np.asarray(self.keypoints, np.float32) * KEYPOINT_STEP), 0, 65535) / KEYPOINT_STEP
        scales = np.asarray(self.scales, np.float16).astype(np.float32)
        return Features(kp.astype(np.float32), d, scales, self.metric)

    @classmethod
    def empty(cls, dim: int = 128, dtype: type = np.float32, metric: str = "l2") -> "Features":
        """No feature, with the right shapes: ``(0, 2)``, ``(0, dim)``, ``(0,)``."""
        return cls(np.zeros((0, 2), np.float32), np.zeros((0, dim), dtype), np.zeros((0,), np.float32), metric)


class FeatureExtractor:
    """Base: ``extract(image) -> Features``. Subclasses set ``default_conf`` and implement ``_detect``."""

    default_conf: dict[str, Any] = {}
    conf_rules: dict[str, Any] = {}
    descriptor_dim = 0
    descriptor_dtype: type = np.float32
    metric = "l2"  #: how this extractor's descriptors are compared (stored in every ``Features``)

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "features")

    def extract(self, image: np.ndarray) -> Features:
        """Any accepted image (grey/BGR, 8/16-bit, any size) -> ``Features`` (empty, right shapes, if none found)."""
        return self.extract_prepared(*self.prepare(image))

    def prepare(self, image: np.ndarray) -> tuple[np.ndarray, float]:
        """The grey uint8 ``(h, w)`` image extraction runs on (downscaled to ``resize_max``) and its scale to the
        original: ``extract_prepared(*prepare(image))`` is ``extract(image)``, so a kept copy of the prepared image
        (lossless) gives the same features later."""
        gray = to_gray_u8(image)
        scale = 1.0
        resize_max = self.conf.get("resize_max")
        if resize_max and max(gray.shape) > resize_max:
            scale = resize_max / max(gray.shape)
            gray = cv2.resize(gray, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        return gray, scale

    def extract_prepared(self, gray: np.ndarray, scale: float = 1.0) -> Features:
        """Features of a ``prepare``d grey uint8 image; keypoints and scales divided by ``scale``."""
        kps, desc = self._detect(gray)
        if not kps:
            return Features.empty(self.descriptor_dim, self.descriptor_dtype, self.metric)
        pts = np.array([k.pt for k in kps], np.float32) / scale
        sizes = np.array([k.size for k in kps], np.float32) / scale
        return Features(pts, np.ascontiguousarray(desc, dtype=self.descriptor_dtype), sizes, self.metric)

    def _detect(self, gray: np.ndarray) -> tuple[list, np.ndarray | None]:
        raise NotImplementedError


FEATURES: Registry[FeatureExtractor] = Registry("feature extractor")


@FEATURES.register("sift")
class SIFT(FeatureExtractor):
    """OpenCV SIFT (Lowe 2004), optionally RootSIFT-normalised."""

    default_conf: dict[str, Any] = {
        "name": "sift",  # extractor, by registry name
        "resize_max": 512,  # downscale so the longer side is at most this (None: full resolution); never upscales
        "max_features": 500,  # keep at most this many keypoints, strongest first
        "contrast_threshold": 0.04,  # SIFT DoG contrast threshold (OpenCV default)
        "edge_threshold": 10,  # SIFT edge-response threshold (OpenCV default)
        "n_octave_layers": 3,  # scales per octave (OpenCV default)
        "root_sift": False,  # L1-normalise then square-root descriptors (Arandjelovic & Zisserman 2012)
    }
    conf_rules: dict[str, Any] = {"resize_max": Int(16, optional=True), "max_features": Int(1, 100_000),
                                  "contrast_threshold": Float(0, lo_open=True), "edge_threshold": Float(0, lo_open=True),
                                  "n_octave_layers": Int(1, 16), "root_sift": Bool()}
    descriptor_dim = 128

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        c = self.conf
        self._sift = cv2.SIFT_create(nfeatures=c["max_features"], nOctaveLayers=c["n_octave_layers"],
                                     contrastThreshold=c["contrast_threshold"], edgeThreshold=c["edge_threshold"])

    def _detect(self, gray: np.ndarray) -> tuple[list, np.ndarray | None]:
        kps, desc = self._sift.detectAndCompute(gray, None)
        if desc is not None and len(kps) > self.conf["max_features"]:  # OpenCV may keep ties beyond the cap
            kps, desc = kps[: self.conf["max_features"]], desc[: self.conf["max_features"]]
        if desc is not None and self.conf["root_sift"]:
            desc = np.sqrt(desc / np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)) * 512.0
        return list(kps), desc


def create_extractor(conf: dict[str, Any] | None = None) -> FeatureExtractor:
    """The extractor named by ``conf["name"]`` (default ``"sift"``), configured by the rest of ``conf``."""
    name = (conf or {}).get("name", "sift")
    return FEATURES.get(name)(conf)


@FEATURES.register("orb")
class ORB(FeatureExtractor):
    """OpenCV ORB (Rublee et al. 2011): 256-bit binary descriptors packed in 32 bytes, compared by Hamming distance.

    MILD (Han & Fang 2017) uses 800 per image."""

    default_conf: dict[str, Any] = {
        "name": "orb",  # extractor, by registry name
        "resize_max": None,  # downscale so the longer side is at most this (None: full resolution); never upscales
        "max_features": 800,  # keep at most this many keypoints, strongest first (MILD: 800)
        "scale_factor": 1.2,  # pyramid decimation ratio (OpenCV default)
        "n_levels": 8,  # pyramid levels (OpenCV default)
        "fast_threshold": 20,  # FAST corner threshold (OpenCV default)
    }
    conf_rules: dict[str, Any] = {"resize_max": Int(16, optional=True), "max_features": Int(1, 100_000),
                                  "scale_factor": Float(1, 4, lo_open=True), "n_levels": Int(1, 32),
                                  "fast_threshold": Int(1, 255)}
    descriptor_dim = 32
    descriptor_dtype = np.uint8
    metric = "hamming"

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        c = self.conf
        self._orb = cv2.ORB_create(nfeatures=c["max_features"], scaleFactor=c["scale_factor"], nlevels=c["n_levels"],
                                   fastThreshold=c["fast_threshold"])

    def _detect(self, gray: np.ndarray) -> tuple[list, np.ndarray | None]:
        kps, desc = self._orb.detectAndCompute(gray, None)
        if desc is not None and len(kps) > self.conf["max_features"]:
            kps, desc = kps[: self.conf["max_features"]], desc[: self.conf["max_features"]]
        return list(kps), desc
