"""Baseline global descriptors a user would otherwise pick, registered beside ``cae`` in ``DESCRIPTORS``.

- ``thumbnail``: the raw-pixel descriptor of PTAM-style relocalisers (Klein & Murray 2008): the grey image shrunk to
  a small thumbnail (area averaging), zero-mean, L2-normalised. Conf ``{"descriptor": {"name": "thumbnail"}}``.
- ``bovw``: bag of visual words (Sivic & Zisserman 2003) over the frame's own SIFT descriptors: each descriptor
  votes for its nearest visual word, the histogram is tf-idf weighted and L2-normalised (cosine = normalised
  tf-idf dot product). The vocabulary (k-means centroids and idf) is learned once with ``build_vocabulary`` on a
  training image set, and named by ``{"descriptor": {"name": "bovw", "vocabulary": "vocab.npz"}}``.

Both go through the same verification as the CAE code; only the retrieval stage changes.

    >>> build_vocabulary("kitti/sequences/07", "runs/vocab.npz", k=1000)          # doctest: +SKIP
    >>> LoopDetector({"descriptor": {"name": "bovw", "vocabulary": "runs/vocab.npz"}})  # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
import json
import logging
from pathlib import Path
from typing import Any, Sequence

import cv2
import faiss
import numpy as np

from cae_lcd.core.conf import ConfigError, Float, Int, Text
from cae.encode import normalize_codes
from cae_lcd.core.images import read_image, to_gray_u8
from verify.features import Features, create_extractor

from .descriptors import DESCRIPTORS, GlobalDescriptor
from .sequences import open_sequence

__all__ = ["ThumbnailDescriptor", "BoVWDescriptor", "build_vocabulary", "load_vocabulary", "VOCABULARY_VERSION"]

log = logging.getLogger(__name__)

VOCABULARY_VERSION = 2


def _unit_vector(v: np.ndarray) -> np.ndarray:
    return normalize_codes(np.asarray(v, np.float32).reshape(1, -1))[0]


@DESCRIPTORS.register("thumbnail")
class ThumbnailDescriptor(GlobalDescriptor):
    """Grey thumbnail, zero-mean, unit norm (PTAM-style small blurry image); ``dim = width * height``."""

    default_conf: dict[str, Any] = {
        "name": "thumbnail",  # global descriptor, by registry name
        "width": 64,  # thumbnail width, pixels (PTAM: 40x30 at its coarsest pyramid level)
        "height": 48,  # thumbnail height, pixels
        "blur": 0.0,  # extra Gaussian blur of the thumbnail, sigma in thumbnail pixels (0: area averaging only)
    }
    conf_rules: dict[str, Any] = {"width": Int(2, 1024), "height": Int(2, 1024), "blur": Float(0, 100)}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        w, h = int(self.conf["width"]), int(self.conf["height"])
        if w < 2 or h < 2:
            raise ConfigError(f"descriptor.width and descriptor.height must be >= 2; got {w}x{h}")
        self.size = (w, h)
        self.dim = w * h
        self.identity = f"thumbnail:{w}x{h}:blur{float(self.conf['blur']):g}"

    def __call__(self, image: np.ndarray, features: Features | None = None,
                 network_image: np.ndarray | None = None) -> np.ndarray:
        small = cv2.resize(to_gray_u8(image), self.size, interpolation=cv2.INTER_AREA).astype(np.float32)
        if self.conf["blur"]:
            small = cv2.GaussianBlur(small, (0, 0), float(self.conf["blur"]))
        return _unit_vector(small - small.mean())


def _image_paths(images: str | Path | Sequence[str | Path]) -> list[Path]:
    """A sequence folder (KITTI layout or plain images) or a list of image files -> image paths."""
    if isinstance(images, (str, Path)):
        return list(open_sequence(images).frames)
    return [Path(p) for p in images]


def _vocab_key(paths: Sequence[Path], k: int, features_conf: dict[str, Any] | None, max_images: int | None,
               seed: int) -> str:
    payload = json.dumps({"images": [str(p.resolve()) for p in paths], "k": k, "features": features_conf or {},
                          "max_images": max_images, "seed": seed, "version": VOCABULARY_VERSION}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def build_vocabulary(images: str | Path | Sequence[str | Path], out: str | Path, k: int = 1000,
                     features_conf: dict[str, Any] | None = None, max_images: int | None = None,
                     points_per_word: int = 64, niter: int = 15, seed: int = 0) -> Path:
    """Learns a visual vocabulary (faiss k-means over local descriptors) and its idf; cached as ``.npz``.

    Train it on images that are NOT the ones evaluated (e.g. KITTI 07 when evaluating 90), with the same
    ``features`` conf the detector uses.

    Args:
        images: a sequence folder (KITTI layout or plain image folder) or a list of image files.
        out: the ``.npz`` to write; an existing file built from the same images and settings is reused as is.
        k: number of visual words.
        features_conf: local-feature conf (the detector's ``features`` section); None = SIFT defaults.
        max_images: use at most this many images (evenly spaced); None = all.
        points_per_word: k-means trains on at most ``k * points_per_word`` descriptors (random subset).
        niter: k-means iterations.
        seed: seeds the subset and k-means.

    Returns:
        ``out`` (``centroids (k, D)`` float32, ``idf (k,)`` float32 = ``ln((1 + N) / (1 + n_w)) + 1`` over the
        ``N`` training images, ``n_w`` of which contain word ``w``; ``key``, ``meta`` JSON).

    Raises:
        ConfigError: no images, or fewer descriptors than ``k``.
    """
    out = Path(out)
    paths = _image_paths(images)
    if max_images and len(paths) > max_images:
        paths = [paths[i] for i in np.linspace(0, len(paths) - 1, max_images).round().astype(int)]
    if not paths:
        raise ConfigError("build_vocabulary: no images given")
    key = _vocab_key(paths, k, features_conf, max_images, seed)
    if out.is_file():
        with np.load(out) as f:
            if str(f["key"]) == key:
                log.info("vocabulary %s is up to date (k=%d, %d images)", out, k, len(paths))
                return out
    extractor = create_extractor(features_conf)
    per_image = [extractor.extract(read_image(p)).descriptors.astype(np.float32) for p in paths]
    desc = np.concatenate([d for d in per_image if len(d)] or [np.zeros((0, 128), np.float32)])
    if len(desc) < k:
        raise ConfigError(f"build_vocabulary: {len(desc)} descriptors from {len(paths)} images, need at least k={k}")
    rng = np.random.default_rng(seed)
    train = desc[rng.choice(len(desc), k * points_per_word, replace=False)] if len(desc) > k * points_per_word else desc
    km = faiss.Kmeans(desc.shape[1], k, niter=niter, seed=seed, max_points_per_centroid=points_per_word,
                      verbose=False)
    km.train(np.ascontiguousarray(train))
    centroids = np.ascontiguousarray(km.centroids, np.float32)
    quantizer = faiss.IndexFlatL2(centroids.shape[1])
    quantizer.add(centroids)
    doc_freq = np.zeros(k, np.float64)
    for d in per_image:
        if len(d):
            doc_freq[np.unique(quantizer.search(d, 1)[1][:, 0])] += 1
    # smoothed idf (as scikit-learn's): a word seen in every training image keeps weight 1 instead of 0
    idf = (np.log((1.0 + len(per_image)) / (1.0 + doc_freq)) + 1.0).astype(np.float32)
    meta = {"images": len(paths), "descriptors": int(len(desc)), "trained_on": int(len(train)),
            "source": str(paths[0].parent), "features": features_conf or {}, "k": k, "niter": niter}
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp.npz")
    np.savez(tmp, centroids=centroids, idf=idf, key=np.array(key), meta=np.array(json.dumps(meta)),
             version=np.array(VOCABULARY_VERSION))
    tmp.replace(out)
    log.info("vocabulary %s: k=%d from %d descriptors of %d images", out, k, len(desc), len(paths))
    return out


def load_vocabulary(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``centroids (k, D)`` float32 and ``idf (k,)`` float32 from a ``build_vocabulary`` file.

    Raises:
        ConfigError: missing or unreadable file.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"vocabulary not found: {path} (build one with retrieval.baselines.build_vocabulary)")
    try:
        with np.load(path) as f:
            centroids, idf = np.asarray(f["centroids"], np.float32), np.asarray(f["idf"], np.float32)
    except (OSError, KeyError, ValueError) as err:
        raise ConfigError(f"cannot read vocabulary {path}: {err}") from None
    if centroids.ndim != 2 or idf.shape != (len(centroids),):
        raise ConfigError(f"{path}: centroids {centroids.shape} and idf {idf.shape} do not fit")
    return centroids, idf


@DESCRIPTORS.register("bovw")
class BoVWDescriptor(GlobalDescriptor):
    """tf-idf bag of visual words over the frame's local descriptors; ``dim = k`` words."""

    default_conf: dict[str, Any] = {
        "name": "bovw",  # global descriptor, by registry name
        "vocabulary": None,  # .npz written by retrieval.baselines.build_vocabulary (required)
    }
    conf_rules: dict[str, Any] = {"vocabulary": Text(optional=True)}
    needs_features = True

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        super().__init__(conf)
        if not self.conf["vocabulary"]:
            raise ConfigError("descriptor 'bovw' needs descriptor.vocabulary: a .npz from "
                              "retrieval.baselines.build_vocabulary")
        self.centroids, self.idf = load_vocabulary(self.conf["vocabulary"])
        self.quantizer = faiss.IndexFlatL2(self.centroids.shape[1])
        self.quantizer.add(self.centroids)
        self.dim = len(self.centroids)
        digest = hashlib.sha256(self.centroids.tobytes() + self.idf.tobytes()).hexdigest()[:16]
        self.identity = f"bovw:{self.dim}:{digest}"
        self._extractor = None

    def words(self, descriptors: np.ndarray) -> np.ndarray:
        """Nearest visual word of each ``(N, D)`` descriptor -> ``(N,)`` int64."""
        d = np.ascontiguousarray(descriptors, np.float32).reshape(-1, self.centroids.shape[1])
        return self.quantizer.search(d, 1)[1][:, 0] if len(d) else np.zeros(0, np.int64)

    def __call__(self, image: np.ndarray, features: Features | None = None,
                 network_image: np.ndarray | None = None) -> np.ndarray:
        if features is None:  # used on its own, outside the detector: extract SIFT with the defaults
            self._extractor = self._extractor or create_extractor(None)
            features = self._extractor.extract(image)
        words = self.words(features.descriptors)
        if len(words) == 0:
            return np.zeros(self.dim, np.float32)
        tf = np.bincount(words, minlength=self.dim).astype(np.float32) / len(words)
        return _unit_vector(tf * self.idf)
