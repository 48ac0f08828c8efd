"""A code normalisation learned from the user's own images: PCA-whitening with shrinkage, then L2.

The raw CAE code (4096-d, Leonardi & Stahl) is dominated by a few directions that every image of a camera or a
season shares, so cosine similarity between two unrelated frames of the same sequence is high and a change of season
moves every code the same way. Whitening removes the mean, keeps the ``dim`` leading principal components and
divides each by the square root of its variance (plus ``shrink`` times the mean kept variance, which keeps the
smallest components from turning noise into signal when few images were seen). After whitening, unrelated frames
score near 0 with a spread of about ``1 / sqrt(dim)``, on any camera: the calibration relies on that.

Fitted by ``cae-lcd train`` on the training folder (saved in the checkpoint beside the weights) or, by default, on
the sequence being processed (``retrieval.calibrate``). Numpy in, numpy out.

    >>> w = Whitening.fit(codes, dim=256)      # codes (N, D) float32   # doctest: +SKIP
    >>> w.transform(codes).shape                # (N, min(dim, N // 4))   # doctest: +SKIP
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from cae_lcd.core.errors import ConfigError

__all__ = ["Whitening", "MIN_FIT_CODES", "DEFAULT_DIM", "DEFAULT_SHRINK"]

MIN_FIT_CODES = 8  #: fewest codes a whitening can be fitted on
DEFAULT_DIM = 256  #: length of the whitened code (training and detection default)
SAMPLES_PER_DIM = 4  #: a kept component needs this many fitting codes (fewer: the whitening learns the noise)
DEFAULT_SHRINK = 0.1  #: variance shrinkage, times the mean kept variance (training and detection default)


@dataclass(frozen=True)
class Whitening:
    """``y = normalise((x - mean) @ projection.T)``.

    Attributes:
        mean: ``(D,)`` float32, the mean code of the fitting set.
        projection: ``(d, D)`` float32, principal directions divided by their shrunk standard deviations.
        variance: ``(d,)`` float64, the variance of the fitting set along each kept direction (for reports).
        fitted_on: how many codes it was fitted on.
    """

    mean: np.ndarray
    projection: np.ndarray
    variance: np.ndarray
    fitted_on: int

    @property
    def dim(self) -> int:
        """Length of the whitened code."""
        return int(self.projection.shape[0])

    @property
    def input_dim(self) -> int:
        return int(self.projection.shape[1])

    @classmethod
    def fit(cls, codes: np.ndarray, dim: int = DEFAULT_DIM, shrink: float = DEFAULT_SHRINK) -> "Whitening":
        """Fits on ``(N, D)`` codes; keeps ``min(dim, N // SAMPLES_PER_DIM, D)`` components.

        Raises:
            ConfigError: fewer than ``MIN_FIT_CODES`` codes, or non-finite codes.
        """
        x = np.asarray(codes, np.float64)
        if x.ndim != 2 or len(x) < MIN_FIT_CODES:
            raise ConfigError(f"whitening needs at least {MIN_FIT_CODES} codes of shape (N, D); got {x.shape}")
        if not np.isfinite(x).all():
            raise ConfigError("whitening: the codes hold NaN or infinite values")
        mean = x.mean(0)
        keep = max(1, min(int(dim), len(x) // SAMPLES_PER_DIM, x.shape[1]))
        s, vt = _principal(x - mean, keep)
        var = s ** 2 / len(x)
        scale = np.sqrt(var + shrink * var.mean() + 1e-12)
        vt = vt * np.sign(vt[:, :1] + 1e-30)  # a fixed sign per direction: equal inputs, equal bytes
        return cls(mean.astype(np.float32), (vt / scale[:, None]).astype(np.float32), var, len(x))

    def transform(self, codes: np.ndarray) -> np.ndarray:
        """``(N, D)`` (or ``(D,)``) codes -> ``(N, d)`` (or ``(d,)``) float32, unit L2 norm; empty in, empty out."""
        x = np.asarray(codes, np.float32)
        one = x.ndim == 1
        x = x.reshape(-1, self.input_dim)
        y = (x - self.mean) @ self.projection.T
        y /= np.maximum(np.linalg.norm(y, axis=1, keepdims=True), 1e-12)
        return y[0] if one else y

    def state(self) -> dict[str, Any]:
        """Arrays and numbers for a checkpoint or an HDF5 group (``from_state`` reads it back)."""
        return {"mean": self.mean, "projection": self.projection, "variance": self.variance,
                "fitted_on": int(self.fitted_on)}

    @classmethod
    def from_state(cls, state: dict[str, Any], where: str = "whitening") -> "Whitening":
        """Rebuilds from ``state()``; checks shapes and values.

        Raises:
            ConfigError: missing arrays, wrong shapes or non-finite values (``where`` names the source).
        """
        try:
            mean = np.asarray(state["mean"], np.float32)
            proj = np.asarray(state["projection"], np.float32)
            var = np.asarray(state["variance"], np.float64)
            n = int(state["fitted_on"])
        except (KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"{where}: not a whitening ({type(err).__name__}: {err})") from None
        if mean.ndim != 1 or proj.ndim != 2 or proj.shape[1] != len(mean) or var.shape != (len(proj),) \
                or not (np.isfinite(mean).all() and np.isfinite(proj).all() and np.isfinite(var).all()):
            raise ConfigError(f"{where}: damaged whitening (shapes {mean.shape}, {proj.shape}, {var.shape})")
        return cls(mean, proj, var, n)

    def identity(self) -> str:
        """A short hash of the arrays: equal whitenings, equal identity."""
        h = hashlib.sha256(self.mean.tobytes() + self.projection.tobytes())
        return h.hexdigest()[:16]


def _principal(x: np.ndarray, keep: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``keep`` largest singular values ``(keep,)`` and right singular vectors ``(keep, D)`` of centred codes
    ``x`` ``(N, D)``, float64. With fewer codes than dimensions (a stream's fit: 760 codes of 4096-d, 0.6 s by SVD), from
    the eigenvectors of their ``(N, N)`` Gram matrix (0.1 s; the same directions: only the leading ones are kept,
    at most ``N // SAMPLES_PER_DIM``, far above the rounding of the squared spectrum); else by SVD."""
    n, d = x.shape
    if n >= d:
        _, s, vt = np.linalg.svd(x, full_matrices=False)
        return s[:keep], vt[:keep]
    w, u = np.linalg.eigh(x @ x.T)
    top = np.argsort(w)[::-1][:keep]
    s = np.sqrt(np.maximum(w[top], 0.0))
    return s, (u[:, top].T @ x) / np.maximum(s, 1e-300)[:, None]
