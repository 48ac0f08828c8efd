"""Checkpoints and the shipped default weights.

A checkpoint is ``{"format_version": 1, "conf": <training conf>, "state_dict": <ConvAutoencoder or Encoder>}``
written with ``torch.save``, plus ``"whitening"`` (``cae.whitening.Whitening.state()`` as tensors) when training
fitted one on its images; it is always loaded with ``strict=True``. The conf's ``input_norm`` (``cae.model``;
absent: "none", the paper's) says what the encoder does to an image before its first layer; its ``lowpass``
(``cae.preprocess``; absent: 0, none) the Gaussian a small image is read through before it is brought up.
"""

from __future__ import annotations

import hashlib
import logging
import re
from pathlib import Path
from typing import Any

import torch

from cae_lcd.core.errors import ConfigError
from .model import INPUT_NORMS, ConvAutoencoder, Encoder
from .preprocess import MAX_LOWPASS
from .whitening import Whitening

__all__ = ["DEFAULT_WEIGHTS", "RECONSTRUCTION_WEIGHTS", "CHECKPOINT_VERSION", "DEVICE_PATTERN", "save_checkpoint",
           "load_checkpoint", "load_encoder", "load_autoencoder", "encoder_identity", "resolve_device",
           "checkpoint_whitening", "checkpoint_input_norm", "checkpoint_lowpass", "checkpoint_still_cos", "STILL_COS"]

log = logging.getLogger(__name__)

#: the default: the reconstruction term and the place term (issue 28) on every frame of ../shared, standardised input
#: (BENCHMARKS.md, "Training the shipped weights")
DEFAULT_WEIGHTS = Path(__file__).with_name("weights") / "cae_places.pt"
#: the paper's objective alone (reconstruction, photometric augmentation) on KITTI 00+07 and Nordland summer: the
#: weights the default was trained from, kept for the training study's comparison
RECONSTRUCTION_WEIGHTS = Path(__file__).with_name("weights") / "cae_mixed.pt"
CHECKPOINT_VERSION = 1
#: raw codes of adjacent frames this alike: the camera stood still; for weights whose conf does not say
#: (``still_cos``: the weights' own, below the cosine between a frame's code and its code under one grey level of
#: sensor noise; the paper-input weights: 0.9999 and more)
STILL_COS = 0.999
DEVICE_PATTERN = r"auto|cpu|cuda(:[0-9]+)?"  #: the devices a conf may name


def resolve_device(device: str | torch.device | None = None) -> torch.device:
    """``None``/``"auto"`` -> CUDA when available, else CPU; ``"cpu"``, ``"cuda"``, ``"cuda:N"`` as given.

    Raises:
        ConfigError: an unknown device, or CUDA asked for where there is none (or not that many GPUs).
    """
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if not re.fullmatch(DEVICE_PATTERN, str(device)):
        raise ConfigError(f"device must be auto, cpu, cuda or cuda:N; got {device!r}")
    dev = torch.device(device)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device {device!r} asked for, but no CUDA GPU is available here; use 'cpu' or 'auto'")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"device {device!r} asked for, but only {torch.cuda.device_count()} GPU(s) exist")
    return dev


def save_checkpoint(path: str | Path, model: torch.nn.Module, conf: dict[str, Any],
                    whitening: Whitening | None = None, **extra: Any) -> None:
    """Writes ``{"format_version", "conf", "state_dict", ["whitening"], **extra}`` atomically (temp file, rename);
    the conf's ``input_norm`` and ``lowpass`` are the model's own (``Encoder.input_norm``, ``Encoder.lowpass``),
    whatever ``conf`` says."""
    encoder = getattr(model, "encoder", model)
    if isinstance(encoder, Encoder):
        conf = {**conf, "input_norm": encoder.input_norm, "lowpass": encoder.lowpass}
    if whitening is not None:
        extra["whitening"] = {k: torch.as_tensor(v) for k, v in whitening.state().items()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    torch.save({"format_version": CHECKPOINT_VERSION, "conf": conf, "state_dict": state, **extra}, tmp)
    tmp.replace(path)


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """Reads a checkpoint dict (tensors on CPU).

    Raises:
        ConfigError: missing file, unreadable file, or not a checkpoint of this project.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"weights file not found: {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for a damaged file
        raise ConfigError(f"cannot read weights file {path}: {err.__class__.__name__}: {str(err)[:200]}") from None
    if not isinstance(ckpt, dict) or not isinstance(ckpt.get("state_dict"), dict):
        raise ConfigError(f"{path} is not a cae-loop-closure checkpoint (no 'state_dict')")
    bad = [k for k, v in ckpt["state_dict"].items()
           if isinstance(v, torch.Tensor) and v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise ConfigError(f"weights file {path} holds NaN or infinite values (in {', '.join(bad[:3])}); "
                          "it is damaged or from a diverged training run")
    return ckpt


def _encoder_state(state_dict: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    if any(k.startswith("encoder.") for k in state_dict):
        return {k[len("encoder."):]: v for k, v in state_dict.items() if k.startswith("encoder.")}
    return state_dict


def load_autoencoder(path: str | Path | None = None, device: str | torch.device | None = None) -> ConvAutoencoder:
    """The full autoencoder from a checkpoint (default: the shipped weights), in eval mode."""
    path = path or DEFAULT_WEIGHTS
    ckpt = load_checkpoint(path)
    model = ConvAutoencoder(checkpoint_input_norm(ckpt, path), checkpoint_lowpass(ckpt, path))
    try:
        model.load_state_dict(ckpt["state_dict"], strict=True)
    except RuntimeError as err:
        raise ConfigError(f"weights {path} do not fit the autoencoder: {str(err).splitlines()[0]}") from None
    return model.to(resolve_device(device)).eval()


def load_encoder(path: str | Path | None = None, device: str | torch.device | None = None) -> Encoder:
    """The encoder, ready for inference.

    Args:
        path: a checkpoint written by ``train.py`` (full autoencoder or encoder only); ``None`` loads the weights
            shipped inside the package (no network access).
        device: ``"cpu"``, ``"cuda"``, ... ; ``None`` picks CUDA when available.

    Returns:
        ``Encoder`` in eval mode, channels-last, mapping ``(B, 3, 256, 256)`` in [0, 1] to ``(B, 4096)``.
        Its ``identity`` attribute is a short hash of the weights, their ``input_norm`` and ``lowpass`` (stored in
        keyframe databases); ``input_norm``, ``lowpass`` and ``still_cos`` are the checkpoint's
        (``checkpoint_input_norm``, ``checkpoint_lowpass``, ``checkpoint_still_cos``); ``whitening`` is the
        ``Whitening`` saved with the weights, or None.
    """
    path = path or DEFAULT_WEIGHTS
    ckpt = load_checkpoint(path)
    encoder = Encoder(checkpoint_input_norm(ckpt, path), checkpoint_lowpass(ckpt, path))
    try:
        encoder.load_state_dict(_encoder_state(ckpt["state_dict"]), strict=True)
    except RuntimeError as err:
        raise ConfigError(f"weights {path} do not fit the encoder: {str(err).splitlines()[0]}") from None
    encoder.identity = encoder_identity(encoder)
    encoder.still_cos = checkpoint_still_cos(ckpt, path)
    encoder.whitening = checkpoint_whitening(ckpt, path)
    dev = resolve_device(device)
    return encoder.to(dev, memory_format=torch.channels_last).eval()


def _conf_value(ckpt: dict[str, Any], key: str, default: Any) -> Any:
    """``key`` of the checkpoint's training conf, ``default`` where the conf (or the key) is absent."""
    conf = ckpt.get("conf")
    return conf.get(key, default) if isinstance(conf, dict) else default


def checkpoint_input_norm(ckpt: dict[str, Any], path: str | Path) -> str:
    """The checkpoint's ``input_norm`` (``cae.model.INPUT_NORMS``; "none" where its conf has none)."""
    value = _conf_value(ckpt, "input_norm", "none")
    if value not in INPUT_NORMS:
        raise ConfigError(f"{path}: conf input_norm must be one of {', '.join(INPUT_NORMS)}; got {value!r}")
    return value


def checkpoint_lowpass(ckpt: dict[str, Any], path: str | Path) -> float:
    """The Gaussian sigma these weights read small images through (conf ``lowpass``, ``cae.preprocess``; 0 where
    the conf has none)."""
    value = _conf_value(ckpt, "lowpass", 0.0)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value <= MAX_LOWPASS:
        raise ConfigError(f"{path}: conf lowpass must be a number in [0, {MAX_LOWPASS:g}]; got {value!r}")
    return float(value)


def checkpoint_still_cos(ckpt: dict[str, Any], path: str | Path) -> float:
    """The raw-code cosine at which these weights say the camera stood still (conf ``still_cos``; ``STILL_COS``
    where it has none)."""
    value = _conf_value(ckpt, "still_cos", STILL_COS)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.9 <= value < 1:
        raise ConfigError(f"{path}: conf still_cos must be a number in [0.9, 1); got {value!r}")
    return float(value)


def checkpoint_whitening(ckpt: dict[str, Any], path: str | Path) -> Whitening | None:
    """The whitening saved in a checkpoint, or None when it has none."""
    state = ckpt.get("whitening")
    if state is None:
        return None
    if not isinstance(state, dict):
        raise ConfigError(f"{path}: 'whitening' is not a mapping; the checkpoint is damaged")
    state = {k: v.numpy() if isinstance(v, torch.Tensor) else v for k, v in state.items()}
    return Whitening.from_state(state, f"{path}: whitening")


def encoder_identity(encoder: torch.nn.Module) -> str:
    """A 16-hex-digit hash of the encoder's parameters, its ``input_norm`` and its ``lowpass``: equal weights that
    read their input alike give an equal identity (the paper's encoder, input_norm "none" and no low-pass, hashes
    its parameters alone)."""
    h = hashlib.sha256()
    norm = getattr(encoder, "input_norm", "none")
    if norm != "none":
        h.update(f"input_norm={norm}".encode())
    lowpass = getattr(encoder, "lowpass", 0.0)
    if lowpass:
        h.update(f"lowpass={lowpass:g}".encode())
    for name, tensor in sorted(encoder.state_dict().items()):
        h.update(name.encode())
        h.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]
