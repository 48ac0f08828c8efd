"""The image-quality gate: enough edges, or the frame is not worth a place in the map (Leonardi & Stahl)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from core.conf import Bool, Float, Int, configure
from core.images import resize_square, to_gray_u8

__all__ = ["EdgeGate", "GateResult"]


@dataclass(frozen=True)
class GateResult:
    passed: bool  #: True when the frame has enough edges to be used
    edge_ratio: float  #: edge pixels / all pixels of the square grey image, in [0, 1]


class EdgeGate:
    """Canny edge density on the 256x256 grey image; frames below ``min_edge_ratio`` are gated out."""

    default_conf: dict[str, Any] = {
        "enabled": True,  # False lets every frame through (edge_ratio is still measured)
        "image_size": 256,  # side of the square grey image Canny runs on (paper: the 256x256 network input)
        "canny_low": 100,  # Canny hysteresis low threshold (grey levels)
        "canny_high": 200,  # Canny hysteresis high threshold (grey levels)
        "min_edge_ratio": 0.04,  # pass when edge pixels / all pixels >= this (paper: 4%)
    }
    conf_rules: dict[str, Any] = {"enabled": Bool(), "image_size": Int(16, 4096), "canny_low": Float(0, 1000),
                                  "canny_high": Float(0, 1000), "min_edge_ratio": Float(0, 1)}

    def __init__(self, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "gate")

    def edge_ratio(self, image: np.ndarray) -> float:
        """Edge-pixel ratio of any accepted image (grey/BGR, 8/16-bit, any size)."""
        small = resize_square(to_gray_u8(image), self.conf["image_size"])
        edges = cv2.Canny(small, self.conf["canny_low"], self.conf["canny_high"])
        return float(np.count_nonzero(edges)) / edges.size

    def __call__(self, image: np.ndarray) -> GateResult:
        ratio = self.edge_ratio(image)
        return GateResult(passed=(not self.conf["enabled"]) or ratio >= self.conf["min_edge_ratio"], edge_ratio=ratio)
