"""The image-quality gate: enough edges, or the frame is not worth a place in the map (Leonardi & Stahl).

Two modes (``gate.mode``):

- ``relative`` (default): the edge ratio is measured at the image's own resolution (shrunk to at most
  ``image_size`` on its long side, never enlarged, since enlarging blurs edges away) after stretching its grey levels
  between the 1st and 99th percentile (so exposure does not matter); a frame passes when its ratio is at least
  ``relative`` times the *reference*: the median ratio of the sequence, measured by the calibration
  (``retrieval.calibrate``). Images whose percentile range is under ``min_contrast`` grey levels are flat
  (lens cap, fog, a dark tunnel) and score 0. Works from 64x32 to 4K without tuning.
- ``fixed``: the paper's rule, Canny on the 256x256 square image, ratio >= ``min_edge_ratio`` (an absolute number
  that a small or soft image never reaches).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from cae_lcd.core.conf import Bool, Choice, Float, Int, configure
from cae_lcd.core.images import resize_square, to_gray_u8

__all__ = ["EdgeGate", "GateResult"]


@dataclass(frozen=True)
class GateResult:
    passed: bool  #: True when the frame has enough edges to be used
    edge_ratio: float  #: edge pixels / all pixels of the measured grey image, in [0, 1]


class EdgeGate:
    """Canny edge density; frames below the threshold are gated out (see the module doc for the two modes).

    Args:
        conf: overrides of ``default_conf``.
        reference: the sequence's median edge ratio (``relative`` mode; from the calibration). None: the
            threshold is ``relative * min_edge_ratio`` until a reference is known.
    """

    default_conf: dict[str, Any] = {
        "enabled": True,  # False lets every frame through (edge_ratio is still measured)
        "mode": "relative",  # "relative": to the sequence's median, at native resolution; "fixed": the paper's rule
        "relative": 0.25,  # relative mode: pass at >= this fraction of the sequence's median edge ratio
        "min_contrast": 8,  # relative mode: 1st-99th percentile range (grey levels) under which an image is flat
        "image_size": 256,  # fixed: side of the square image; relative: longest side measured (never enlarged)
        "canny_low": 100,  # Canny hysteresis low threshold (grey levels)
        "canny_high": 200,  # Canny hysteresis high threshold (grey levels)
        "min_edge_ratio": 0.04,  # fixed mode: pass when edge pixels / all pixels >= this (paper: 4%)
    }
    conf_rules: dict[str, Any] = {"enabled": Bool(), "mode": Choice("relative", "fixed"), "relative": Float(0, 1),
                                  "min_contrast": Float(0, 255), "image_size": Int(16, 4096),
                                  "canny_low": Float(0, 1000), "canny_high": Float(0, 1000),
                                  "min_edge_ratio": Float(0, 1)}

    def __init__(self, conf: dict[str, Any] | None = None, reference: float | None = None) -> None:
        self.conf = configure(self, conf, "gate")
        self.reference = reference

    @property
    def threshold(self) -> float:
        """The edge ratio a frame needs."""
        c = self.conf
        if c["mode"] == "fixed":
            return float(c["min_edge_ratio"])
        return float(c["relative"] * (self.reference if self.reference is not None else c["min_edge_ratio"]))

    def edge_ratio(self, image: np.ndarray) -> float:
        """Edge-pixel ratio of any accepted image (grey/BGR, 8/16-bit, any size), measured as ``mode`` says."""
        gray = to_gray_u8(image)
        if self.conf["mode"] == "fixed":
            small = resize_square(gray, self.conf["image_size"])
        else:
            small = _stretched(_shrunk(gray, self.conf["image_size"]), self.conf["min_contrast"])
            if small is None:
                return 0.0
        edges = cv2.Canny(small, self.conf["canny_low"], self.conf["canny_high"])
        return float(np.count_nonzero(edges)) / edges.size

    def __call__(self, image: np.ndarray) -> GateResult:
        ratio = self.edge_ratio(image)
        return GateResult(passed=(not self.conf["enabled"]) or ratio >= self.threshold, edge_ratio=ratio)


def _shrunk(gray: np.ndarray, longest: int) -> np.ndarray:
    h, w = gray.shape
    scale = longest / max(h, w)
    if scale >= 1:
        return gray
    return cv2.resize(gray, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)


def _stretched(gray: np.ndarray, min_contrast: float) -> np.ndarray | None:
    """Grey levels stretched so the 1st and 99th percentiles map to 0 and 255; None for a flat image."""
    lo, hi = np.percentile(gray, (1, 99))
    if hi - lo < max(min_contrast, 1e-6):
        return None
    return np.clip((gray.astype(np.float32) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
