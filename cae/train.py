"""Training the autoencoder on a folder of images (``cae-lcd train --images DIR``, or ``python train.py ...``).

The loss: the paper's reconstruction (sigmoid cross-entropy on the logits, the target the clean frame as the encoder
reads it: standardised with ``input_norm: standardise``, the default) plus,
weighted by ``contrastive``, a place term (``cae.contrastive``: InfoNCE on the code between two views of a frame or
of a frame and its temporal neighbour, ``cae.views``), so that the code keeps the place and drops the light, the
camera and the framing; no labels, each folder read as one sequence in name order. ``init: shipped`` fine-tunes the
package's weights, the codes held near theirs (``anchor``: a term on the distance from the init weights' code).
Seeded 70/30 train/validation split, Adam, mini-batches of 32, validation loss each epoch, best-validation weights
kept (``best.pt``, loadable by ``cae.load_encoder``), resumable from ``last.pt``, the resolved conf saved as
``conf.yaml`` and the loss curves as ``loss.png``.

The paper trained for 5000 epochs on a GPU. The CPU default is 40 epochs with early stopping (patience 8); with the
place term an epoch costs about 0.5 s a frame on 2 busy cores (each frame is encoded in two views).

Every conf value and the device are checked before anything is read or written; images that cannot be read
(corrupt, too small, too large, broken links, folders named like images) are skipped with a warning naming the file
and counted in the summary. The batch order of epoch ``e`` depends only on ``(seed, e)``, so a run resumed from
``last.pt`` ends with exactly the weights of an uninterrupted one.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from cae_lcd.core.progress import progress_bar as tqdm  # a bar on a terminal, log lines in a log

from cae_lcd.core.conf import Choice, ConfigError, Float, Int, Text, check_conf, conf_diff, dump_conf, merge_conf
from cae_lcd.core.errors import ImageError
from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from cae_lcd.core.images import IMAGE_EXTENSIONS, image_entries, read_image
from .contrastive import code_anchor, far_mask, info_nce, neighbour_partners, not_revisits, with_revisits
from .model import INPUT_NORMS, INPUT_SIZE, ConvAutoencoder, Encoder
from .preprocess import MAX_LOWPASS, to_network_u8
from .revisits import mine_revisits
from .encode import CPU_BATCH, encode_images
from .views import default_views, photometric, view_rules, warp
from .weights import (DEFAULT_WEIGHTS, DEVICE_PATTERN, STILL_COS, checkpoint_input_norm, checkpoint_lowpass,
                      checkpoint_still_cos, load_checkpoint, load_encoder, resolve_device, save_checkpoint)
from .whitening import DEFAULT_DIM, DEFAULT_SHRINK, MIN_FIT_CODES, Whitening

__all__ = ["default_conf", "conf_rules", "RANDOM_START_LR", "FINE_TUNE_LR", "list_images", "load_image_folder",
           "sequence_order", "main"]

log = logging.getLogger(__name__)

RANDOM_START_LR = 1.0e-3  #: ``lr`` from a random start (the paper's)
FINE_TUNE_LR = 3.0e-4  #: ``lr`` from init weights (``init``): moved less, they keep what they learned of conditions
#                        the folder lacks (measured: BENCHMARKS.md, "Fine-tuning at a fine-tune's learning rate")

default_conf: dict[str, Any] = {
    "epochs": 40,  # maximum number of epochs (the paper: 5000 on a GPU)
    "batch_size": 32,  # mini-batch size (paper: 32)
    "lr": None,  # Adam learning rate; None = RANDOM_START_LR from a random start (the paper's 1e-3), FINE_TUNE_LR
    #             from init weights
    "val_fraction": 0.3,  # share of images held out for validation (paper: 30%)
    "seed": 0,  # seeds the split, the initialisation and the batch order
    "patience": 8,  # stop after this many epochs without a better validation loss; 0 = never stop early
    "min_delta": 1.0e-5,  # an improvement smaller than this does not count for early stopping
    "device": "auto",  # "auto" (CUDA if present), "cpu", "cuda", "cuda:1", ...
    "max_images": None,  # use at most this many images (a seeded random subset); None = all
    "augment": 0.4,  # photometric augmentation strength (0: none): the input's gain, offset and gamma are jittered
    #                  by up to this fraction and the target stays the clean image (a denoising autoencoder),
    #                  so the code learns to ignore light and exposure (measured: BENCHMARKS.md, training study)
    "input_norm": "standardise",  # what the encoder does to each image first (cae.model.INPUT_NORMS): "standardise"
    #                              (mean 0.5, spread 0.25: light level and contrast removed; the shipped weights')
    #                              or "none" (the paper); a warning where the init weights read their input otherwise
    "lowpass": None,  # Gaussian sigma, in an image's own pixels, that an image smaller than the network on both
    #                  sides is read through before it is brought up (cae.preprocess; saved with the weights, which
    #                  the detector then reads alike); None = the init weights' own (0, none, from a random start)
    "init": None,  # starting weights: None = random N(0, 0.05) (the paper), "shipped" = the weights in the package
    #               (fine-tuning), or a checkpoint path; a run resumed from last.pt keeps its own weights
    "contrastive": 1.0,  # weight of the place term (cae.contrastive, InfoNCE on the code) beside the reconstruction;
    #                     0 = reconstruction only (the paper; then `views` and the keys below are unused)
    "temperature": 0.1,  # the InfoNCE softmax temperature
    "anchor": 10.0,  # weight of a term keeping each changed view's code near the init weights' code of its clean
    #                 frame (cae.contrastive.code_anchor): a fine-tune adapts without forgetting what the init
    #                 weights learned elsewhere (measured: BENCHMARKS.md, training study); acts only with `init`
    #                 and the place term; 0 = none
    "blend": 0.5,  # with `init`: best.pt's weights are this share of the fine-tuned weights plus the rest of the init
    #               weights' (weight-space ensembling, WiSE-FT: Wortsman et al., CVPR 2022; what the init weights knew
    #               of conditions the folder lacks stays; measured: BENCHMARKS.md, training study); 1 = the fine-tuned
    #               weights as trained
    "neighbours": 1,  # positives: two views of a frame, or of a frame and one at most this many frames away in
    #                  its folder (name order = time order; 0 = the frame itself only)
    "far": 20,  # negatives: frames of the batch at least this many frames apart in one folder (or in another
    #            folder); nearer ones are left out of the loss
    "revisit_z": 6.0,  # revisits found in each folder (cae.revisits: a stretch of frames matching another stretch
    #                   at least `far` frames away, this many robust standard deviations above the frame's other
    #                   lines) are positives of the place term and never negatives; 0 = none
    "revisit_span": 5,  # frames either side fused along a pair's line when looking for revisits
    "revisit_every": 4,  # epochs between two searches for revisits with the current weights
    "revisit_share": 0.5,  # probability that a frame with revisits takes one as its partner (else a view/neighbour)
    "recon_share": 0.5,  # share of each batch whose first view is decoded for the reconstruction term (the decoder
    #                     costs 3x the encoder: less is faster; the term is kept, >= one image a batch)
    "threads": None,  # torch CPU threads while training; None = torch's default
    "views": dict(default_views),  # the two views' changes of light, camera and framing (cae.views)
    "whitening_dim": DEFAULT_DIM,  # whitening fitted on all the images' codes, saved in best.pt; 0 = none
    "whitening_shrink": DEFAULT_SHRINK,  # its variance shrinkage (see cae.whitening)
}

conf_rules: dict[str, Any] = {
    "epochs": Int(1),
    "batch_size": Int(1),
    "lr": Float(0, lo_open=True, optional=True),
    "val_fraction": Float(0, 1, lo_open=True, hi_open=True),
    "seed": Int(0),
    "patience": Int(0),
    "min_delta": Float(0),
    "device": Text(DEVICE_PATTERN),
    "max_images": Int(2, optional=True),
    "augment": Float(0, 0.9),
    "whitening_dim": Int(0, 4096),
    "whitening_shrink": Float(0, 100),
    "input_norm": Choice(*INPUT_NORMS),
    "lowpass": Float(0, MAX_LOWPASS, optional=True),
    "init": Text(optional=True),
    "contrastive": Float(0, 100),
    "temperature": Float(0.01, 10),
    "anchor": Float(0, 100),
    "blend": Float(0, 1, lo_open=True),
    "neighbours": Int(0, 1000),
    "far": Int(0, 1_000_000),
    "recon_share": Float(0, 1, lo_open=True),
    "revisit_z": Float(0, 1000),
    "revisit_span": Int(0, 100),
    "revisit_every": Int(1, 100000),
    "revisit_share": Float(0, 1),
    "threads": Int(1, 1024, optional=True),
    "views": {k: Float(lo, hi) for k, (lo, hi) in view_rules.items()},
}

_RESUME_KEYS = ("state_dict", "optimizer", "epoch", "best_val_loss", "best_epoch", "history")


@dataclass
class _Progress:
    """Where training stands: restored from ``last.pt`` or fresh."""

    start_epoch: int = 0
    best_val: float = float("inf")
    best_epoch: int = -1
    history: list[dict[str, float]] = field(default_factory=list)
    revisits: np.ndarray | None = None  #: ``(M, 2)`` training-set indices of the revisits last found (None: not yet)


def list_images(folder: str | Path) -> list[Path]:
    """Every entry below ``folder`` (recursive) named like an image, sorted by path.

    Entries that are not readable image files (broken links, folders named ``x.png``) are listed too, so that
    ``load_image_folder`` reports and counts them.

    Raises:
        ConfigError: the folder is missing, is not a folder, or holds nothing named like an image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"image folder not found: {folder}" if not folder.exists()
                          else f"image folder {folder} is not a folder")
    files = image_entries(folder, recursive=True)
    if not files:
        raise ConfigError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) found below {folder}")
    return files


def load_image_folder(files: Sequence[Path], lowpass: float = 0.0) -> tuple[np.ndarray, list[Path]]:
    """Reads and resizes images to the network size (``cae.preprocess.to_network_u8``, small ones through the
    ``lowpass`` Gaussian first); unreadable ones are skipped with a warning naming the file.

    Returns:
        ``(N, 256, 256, 3)`` uint8 RGB array and the paths actually used.

    Raises:
        ConfigError: none of the images could be read.
    """
    arrays, used = [], []
    for path in tqdm(files, desc="loading images", unit="img", leave=False):
        try:
            arrays.append(to_network_u8(read_image(path), INPUT_SIZE, lowpass))
            used.append(path)
        except ImageError as err:
            log.warning("skipping %s: %s", path, err)
    if not arrays:
        raise ConfigError(f"none of the {len(files)} images could be read")
    return np.stack(arrays), used


def _check_out(out: Path) -> None:
    """Fails early, before images are read, when ``out`` can never become a folder (it or a parent is a file)."""
    for path in (out, *out.parents):
        if os.path.lexists(path):
            if not path.is_dir():
                raise ConfigError(f"--out {out}: {'it' if path == out else path} exists and is not a folder")
            return


def _prepare(images: str | Path | Sequence[str | Path], out: Path, conf: dict[str, Any] | None
             ) -> tuple[dict[str, Any], torch.device, list[str], list[Path]]:
    """Checks the conf, the device, the output path and the image folders; reads only the init weights' conf (for
    ``lowpass``), resolves ``lr`` by ``init`` and writes nothing.

    Returns:
        The resolved conf, the device, the image folders and the image files to read (``max_images`` applied).

    Raises:
        ConfigError: an unknown conf key or a bad value, an unavailable device, an output path under a file, a
            missing or empty image folder.
    """
    conf = merge_conf(default_conf, conf)
    check_conf(conf, conf_rules)
    device = resolve_device(conf["device"])
    if conf["contrastive"] and conf["far"] <= conf["neighbours"]:
        raise ConfigError(f"'far' ({conf['far']}) must be larger than 'neighbours' ({conf['neighbours']}): a "
                          "positive cannot also be a negative")
    init = _init_path(conf)  # a missing init file is named before anything is written
    if conf["lowpass"] is None:
        conf["lowpass"] = 0.0 if init is None else checkpoint_lowpass(load_checkpoint(init), init)
    if conf["lr"] is None:
        conf["lr"] = RANDOM_START_LR if init is None else FINE_TUNE_LR
    _check_out(out)
    folders = [str(images)] if isinstance(images, (str, Path)) else [str(f) for f in images]
    if not folders:
        raise ConfigError("no image folder given")
    files = list(dict.fromkeys(f for folder in folders for f in list_images(folder)))
    if conf["max_images"] and len(files) > conf["max_images"]:
        rng = np.random.default_rng(conf["seed"])
        files = sorted(rng.choice(np.array(files, dtype=object), conf["max_images"], replace=False).tolist())
    return conf, device, folders, files


@dataclass
class _Frames:
    """Training frames and where each stands in its sequence (a folder, read in name order)."""

    images: np.ndarray  #: ``(N, 256, 256, 3)`` uint8 RGB
    folder: np.ndarray  #: ``(N,)`` int, the frame's folder
    position: np.ndarray  #: ``(N,)`` int, its rank in that folder

    def __len__(self) -> int:
        return len(self.images)

    def take(self, idx: np.ndarray) -> "_Frames":
        return _Frames(self.images[idx], self.folder[idx], self.position[idx])


def sequence_order(files: Sequence[Path]) -> tuple[np.ndarray, np.ndarray]:
    """Each file's folder (an id per parent directory) and its rank among that folder's files, in path order.

    Returns:
        ``(N,)`` int folder ids and ``(N,)`` int positions.
    """
    parents: dict[Path, list[int]] = {}
    for i, f in enumerate(files):
        parents.setdefault(Path(f).parent, []).append(i)
    folder, position = np.zeros(len(files), np.int64), np.zeros(len(files), np.int64)
    for fid, members in enumerate(parents.values()):
        ordered = sorted(members, key=lambda i: str(files[i]))
        folder[ordered], position[ordered] = fid, np.arange(len(ordered))
    return folder, position


def _split(frames: _Frames, files: list[Path], conf: dict[str, Any]) -> tuple[_Frames, _Frames, dict[str, list[str]]]:
    """Seeded train/validation split.

    Returns:
        Training frames, validation frames, and ``{"train": [paths], "val": [paths]}`` (for ``split.json``).

    Raises:
        ConfigError: fewer than 2 images (no split possible).
    """
    if len(frames) < 2:
        raise ConfigError(f"need at least 2 readable images to train with a validation split; found {len(frames)}")
    order = np.random.default_rng(conf["seed"]).permutation(len(frames))
    n_val = min(len(frames) - 1, max(1, int(round(conf["val_fraction"] * len(frames)))))
    val_idx, train_idx = np.sort(order[:n_val]), np.sort(order[n_val:])
    split = {"train": [str(files[i]) for i in train_idx], "val": [str(files[i]) for i in val_idx]}
    return frames.take(train_idx), frames.take(val_idx), split


def _init_path(conf: dict[str, Any]) -> Path | None:
    """The checkpoint ``init`` names (``"shipped"``: the package's weights), or None for a random start.

    Raises:
        ConfigError: the file is missing.
    """
    if not conf["init"]:
        return None
    path = DEFAULT_WEIGHTS if conf["init"] == "shipped" else Path(conf["init"])
    if not path.is_file():
        raise ConfigError(f"init: weights file not found: {path} (use 'shipped', a checkpoint path, or null)")
    return path


def _initial_weights(conf: dict[str, Any]) -> Path | None:
    """``_init_path``, with a warning where those weights read their input otherwise than ``input_norm``."""
    path = _init_path(conf)
    if path is not None and (theirs := checkpoint_input_norm(load_checkpoint(path), path)) != conf["input_norm"]:
        log.warning("init: %s was trained with input_norm %r; training with %r (its weights start reading standardised "
                    "or raw images they were not trained on; set input_norm: %s to keep its own)", path, theirs,
                    conf["input_norm"], theirs)
    return path


def _teacher(conf: dict[str, Any], device: torch.device) -> Encoder | None:
    """The init weights' encoder, frozen, that ``anchor`` measures the codes against (None without ``anchor``, ``init``
    or the place term)."""
    if not (conf["anchor"] and conf["init"] and conf["contrastive"]):
        return None
    return load_encoder(_init_path(conf), device).requires_grad_(False)


def _resume_or_start(last_path: Path, conf: dict[str, Any], device: torch.device, val_set: _Frames,
                     restart: bool, teacher: Encoder | None
                     ) -> tuple[ConvAutoencoder, torch.optim.Optimizer, _Progress]:
    """A seeded model and optimizer, restored from ``last_path`` when it exists (unless ``restart``).

    Raises:
        ConfigError: ``last_path`` is damaged, not a training checkpoint, or does not fit the model.
    """
    torch.manual_seed(conf["seed"])
    model = ConvAutoencoder(conf["input_norm"], conf["lowpass"])
    init = _initial_weights(conf)
    if init is not None and (restart or not last_path.exists()):
        try:
            model.load_state_dict(load_checkpoint(init)["state_dict"], strict=True)
        except RuntimeError as err:
            raise ConfigError(f"init: {init} does not fit the autoencoder: {str(err).splitlines()[0]}") from None
        log.info("starting from the weights in %s", init)
    model = model.to(device, memory_format=torch.channels_last)
    optim = torch.optim.Adam(model.parameters(), lr=conf["lr"])
    if restart or not last_path.exists():
        val = _evaluate(model, val_set, conf, device, teacher)
        log.info("initial validation loss %.5f", val)
        return model, optim, _Progress(history=[{"epoch": 0, "train_loss": float("nan"), "val_loss": val,
                                                 "seconds": 0.0}])
    hint = "; run with --restart (restart=True) to start over"
    try:
        state = load_checkpoint(last_path)
    except ConfigError as err:
        raise ConfigError(f"{err}{hint}") from None
    missing = [k for k in _RESUME_KEYS if k not in state]
    if missing:
        raise ConfigError(f"{last_path} is not a training checkpoint (no {', '.join(missing)}){hint}")
    try:
        model.load_state_dict(state["state_dict"], strict=True)
        optim.load_state_dict(state["optimizer"])
    except (RuntimeError, ValueError, KeyError) as err:
        raise ConfigError(f"{last_path} does not fit the autoencoder: {str(err).splitlines()[0]}{hint}") from None
    changed = [k for k in conf_diff(state.get("conf") or {}, conf) if k != "epochs"]
    if changed:
        log.warning("resuming %s with changed conf: %s (the checkpoint's weights are kept)", last_path,
                    ", ".join(changed))
    progress = _Progress(int(state["epoch"]), float(state["best_val_loss"]), int(state["best_epoch"]),
                         list(state["history"]),
                         None if state.get("revisits") is None else state["revisits"].numpy().astype(np.int64))
    log.info("resuming from %s after epoch %d (best validation loss %.5f)", last_path, progress.start_epoch,
             progress.best_val)
    return model, optim, progress


def _to_batch(images: np.ndarray, device: torch.device) -> torch.Tensor:
    x = torch.from_numpy(images).to(device).permute(0, 3, 1, 2).float().div_(255.0)
    return x.contiguous(memory_format=torch.channels_last)


def _evaluate(model: ConvAutoencoder, frames: _Frames, conf: dict[str, Any], device: torch.device,
              teacher: Encoder | None = None) -> float:
    """Validation loss: reconstruction of the clean frames, plus ``contrastive`` times the place term on two views
    of each frame drawn from a fixed seed (the same views every epoch), plus ``anchor`` times the first view's
    distance from the ``teacher``'s code of its clean frame."""
    model.eval()
    total, batch = 0.0, conf["batch_size"]
    rng = np.random.default_rng([conf["seed"], 2**31])
    with torch.inference_mode():
        for start in range(0, len(frames), batch):
            x = _to_batch(frames.images[start:start + batch], device)
            total += F.binary_cross_entropy_with_logits(model(x), model.encoder.network_input(x),
                                                        reduction="sum").item() / x[0].numel()
            if conf["contrastive"] and len(x) > 1:
                views = [_view(x, rng, conf) for _ in range(2)]
                a, b = (model.encoder.forward_map(v[1]).flatten(1) for v in views)
                neg = torch.as_tensor(far_mask(frames.folder[start:start + batch], frames.position[start:start + batch],
                                               conf["far"]))
                total += conf["contrastive"] * info_nce(a, b, neg, conf["temperature"]).item() * len(x)
                if teacher is not None:
                    held = teacher.forward_map(views[0][0]).flatten(1)  # the clean frames' codes, as in training
                    total += conf["anchor"] * code_anchor(a, held).item() * len(x)
    return total / max(1, len(frames))


def _view(x: torch.Tensor, rng: np.random.Generator, conf: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor]:
    """A view of each image: ``(warped clean target, warped and photometrically changed input)``."""
    geo = warp(x, rng, conf["views"]["crop"], conf["views"]["rotate"])
    return geo, photometric(geo, rng, conf["augment"], conf["views"])


def _place_step(model: ConvAutoencoder, train_set: _Frames, picks: np.ndarray, rng: np.random.Generator,
                conf: dict[str, Any], device: torch.device, revisits: np.ndarray,
                teacher: Encoder | None = None) -> float:
    """One batch with the place term, its gradient accumulated (``backward`` done here; returns the loss): two views
    (of a frame and of a temporal neighbour or a revisit), both encoded; the first ``recon_share`` of the first views
    decoded and scored against their warped clean frames. With a ``teacher`` (the init weights' frozen encoder,
    ``anchor`` > 0), ``anchor`` times ``code_anchor`` of the first views' codes against the teacher's codes of their
    clean frames is added to the place term.

    On the CPU the network runs on ``CPU_BATCH`` images at a time, where its activations stay in the cache (1.75x
    faster a step than the whole batch at once): the codes first without a graph, the place term's gradient with
    respect to them, then each chunk again with its graph, back-propagating that gradient and its share of the
    reconstruction (gradient caching: the gradient of the whole batch, up to float rounding). On a GPU, one pass."""
    partners = neighbour_partners(train_set.folder, train_set.position, picks, conf["neighbours"], rng)
    partners = with_revisits(partners, picks, revisits, conf["revisit_share"], rng)
    target, view_a = _view(_to_batch(train_set.images[picks], device), rng, conf)
    _, view_b = _view(_to_batch(train_set.images[partners], device), rng, conf)
    n_rec = max(1, int(round(conf["recon_share"] * len(picks))))
    neg = torch.as_tensor(far_mask(train_set.folder[picks], train_set.position[picks], conf["far"])
                          & not_revisits(picks, revisits))
    chunk = CPU_BATCH if device.type == "cpu" else len(picks)
    cached = chunk < len(picks)  # gradient caching only where the batch is cut into chunks (a GPU: one pass)
    with torch.set_grad_enabled(not cached):
        maps = [torch.cat([model.encoder.forward_map(v) for v in view.split(chunk)]) for view in (view_a, view_b)]
    codes = [m.flatten(1).requires_grad_() if cached else m.flatten(1) for m in maps]
    place = conf["contrastive"] * info_nce(codes[0], codes[1], neg, conf["temperature"])
    if teacher is not None:  # the first views' codes against the init weights' codes of their clean frames
        with torch.no_grad():
            held = torch.cat([teacher.forward_map(t) for t in target.split(chunk)]).flatten(1)
        place = place + conf["anchor"] * code_anchor(codes[0], held)
    if not cached:
        recon = _reconstruction(model, maps[0][:n_rec], target[:n_rec], target[:n_rec].numel())
        (place + recon).backward()
        return place.item() + recon.item()
    place.backward()
    total = place.item()
    for view, code in zip((view_a, view_b), codes):
        for start in range(0, len(view), chunk):
            part = model.encoder.forward_map(view[start:start + chunk])
            loss = (part.flatten(1) * code.grad[start:start + chunk]).sum()
            rec = range(start, min(start + chunk, n_rec)) if view is view_a else range(0)
            if len(rec):  # the reconstruction's share: its mean over the decoded first views, in parts
                err = _reconstruction(model, part[:len(rec)], target[rec.start:rec.stop], target[:n_rec].numel())
                total += err.item()
                loss = loss + err
            loss.backward()
    return total


def _reconstruction(model: ConvAutoencoder, code_maps: torch.Tensor, targets: torch.Tensor, count: int) -> torch.Tensor:
    """The reconstruction term's share of ``code_maps`` ``(b, 16, 16, 16)`` against their ``targets``
    ``(b, 3, 256, 256)`` (clean images, read as the encoder reads them: ``Encoder.network_input``): the summed binary
    cross-entropy over ``count`` (the elements of every decoded view)."""
    return F.binary_cross_entropy_with_logits(model.decoder(code_maps), model.encoder.network_input(targets),
                                              reduction="sum") / count


def _train_epoch(model: ConvAutoencoder, optim: torch.optim.Optimizer, train_set: _Frames, epoch: int,
                 conf: dict[str, Any], device: torch.device, revisits: np.ndarray,
                 teacher: Encoder | None = None) -> float:
    """One pass over ``train_set`` in a batch order seeded by ``(seed, epoch)``; returns the mean training loss."""
    model.train()
    rng = np.random.default_rng([conf["seed"], epoch])
    perm = rng.permutation(len(train_set))
    total = 0.0
    for start in range(0, len(perm), conf["batch_size"]):
        picks = np.sort(perm[start:start + conf["batch_size"]])
        optim.zero_grad(set_to_none=True)
        if conf["contrastive"] and len(picks) > 1:
            value = _place_step(model, train_set, picks, rng, conf, device, revisits, teacher)
        else:
            x = _to_batch(train_set.images[picks], device)
            x_in = _jitter(x, conf["augment"], rng) if conf["augment"] else x
            loss = F.binary_cross_entropy_with_logits(model(x_in), model.encoder.network_input(x))
            loss.backward()
            value = loss.item()
        optim.step()
        total += value * len(picks)
    return total / len(train_set)


def _revisits(model: ConvAutoencoder, train_set: _Frames, conf: dict[str, Any], device: torch.device) -> np.ndarray:
    """``(M, 2)`` training-set indices of the revisits in its folders, found with the current weights' codes
    (``cae.revisits``); none when the place term or ``revisit_z`` is off."""
    if not (conf["contrastive"] and conf["revisit_z"]) or len(train_set) < 2:
        return np.zeros((0, 2), np.int64)
    model.eval()
    codes = encode_images(model.encoder, list(train_set.images), prepared=True)
    found = mine_revisits(codes, train_set.folder, train_set.position, conf["far"], conf["revisit_span"],
                          conf["revisit_z"])
    log.info("revisits: %d of %d frames have one (cae.revisits, z >= %g)", len(np.unique(found[:, 0])),
             len(train_set), conf["revisit_z"])
    return found


def _jitter(x: torch.Tensor, strength: float, rng: np.random.Generator) -> torch.Tensor:
    """Per-image random gain, offset and gamma of ``(B, 3, H, W)`` images in [0, 1] (drawn from ``rng``)."""
    b = len(x)
    gain, offset, gamma = (torch.as_tensor(rng.uniform(lo, hi, (b, 1, 1, 1)), dtype=x.dtype, device=x.device)
                           for lo, hi in ((1 - strength, 1 + strength), (-strength / 2, strength / 2),
                                          (1 - strength, 1 + strength)))
    return (x.clamp(1e-4, 1).pow(gamma) * gain + offset).clamp(0, 1)


def _fit(model: ConvAutoencoder, optim: torch.optim.Optimizer, train_set: _Frames, val_set: _Frames,
         conf: dict[str, Any], device: torch.device, out: Path, progress: _Progress,
         teacher: Encoder | None) -> _Progress:
    """Trains from ``progress.start_epoch`` to ``conf["epochs"]`` (or an early stop); saves ``best.pt``,
    ``last.pt`` and ``loss.png`` after every epoch.

    Raises:
        ConfigError: the loss became NaN or infinite (training diverged; nothing of that epoch is saved).
    """
    bar = tqdm(range(progress.start_epoch, conf["epochs"]), desc="epochs", unit="epoch",
               initial=progress.start_epoch, total=conf["epochs"])
    for epoch in bar:
        t0 = time.perf_counter()
        if progress.revisits is None or epoch % conf["revisit_every"] == 0:
            progress.revisits = _revisits(model, train_set, conf, device)
        train_loss = _train_epoch(model, optim, train_set, epoch, conf, device, progress.revisits, teacher)
        val = _evaluate(model, val_set, conf, device, teacher)
        if not (math.isfinite(train_loss) and math.isfinite(val)):
            raise ConfigError(f"training diverged in epoch {epoch + 1} (loss {train_loss}, validation {val}); "
                              f"lower 'lr' (now {conf['lr']:g}); nothing of this epoch was saved")
        progress.history.append({"epoch": epoch + 1, "train_loss": train_loss, "val_loss": val,
                                 "seconds": time.perf_counter() - t0})
        if val < progress.best_val - conf["min_delta"]:
            progress.best_val, progress.best_epoch = val, epoch + 1
            save_checkpoint(out / "best.pt", model, conf, epoch=epoch + 1, val_loss=val)
        save_checkpoint(out / "last.pt", model, conf, epoch=epoch + 1, optimizer=optim.state_dict(),
                        best_val_loss=progress.best_val, best_epoch=progress.best_epoch, history=progress.history,
                        revisits=torch.as_tensor(progress.revisits))
        _plot_history(progress.history, out / "loss.png")
        bar.set_postfix(train=f"{train_loss:.4f}", val=f"{val:.4f}", best=f"{progress.best_val:.4f}")
        if conf["patience"] and epoch + 1 - progress.best_epoch >= conf["patience"]:
            log.info("early stop: no better validation loss for %d epochs", conf["patience"])
            break
    return progress


def _blend_with_init(model: ConvAutoencoder, theirs: dict[str, torch.Tensor], share: float) -> None:
    """The model's weights become ``share`` x its own + ``(1 - share)`` x ``theirs`` (the init weights; in place)."""
    with torch.no_grad():
        for key, value in model.state_dict().items():
            if value.is_floating_point():
                value.mul_(share).add_(theirs[key].to(value.device, value.dtype), alpha=1.0 - share)


def _finish_best(best: Path, data: np.ndarray, conf: dict[str, Any], device: torch.device) -> Whitening | None:
    """Makes ``best.pt`` what the detector reads: a fine-tune's weights blended with the init weights (``blend``;
    once: a checkpoint that says ``blend`` already is not blended again, so a finished run resumed keeps its
    weights; its ``val_loss`` is the fine-tuned weights' own), the init weights' ``still_cos`` in the conf
    (``cae.weights.checkpoint_still_cos``: a fine-tuned camera keeps the shipped weights' own; ``STILL_COS`` from a
    random start), and the code normalisation fitted on every image's code (``whitening_dim``; returned, None without
    one)."""
    ckpt = load_checkpoint(best)
    model = ConvAutoencoder(conf["input_norm"], conf["lowpass"])
    model.load_state_dict(ckpt["state_dict"], strict=True)
    init = _init_path(conf)
    init_ckpt = None if init is None else load_checkpoint(init)
    extra = {k: v for k, v in ckpt.items() if k not in ("format_version", "conf", "state_dict", "whitening")}
    if init_ckpt is not None and conf["blend"] < 1 and "blend" not in extra:
        _blend_with_init(model, init_ckpt["state_dict"], conf["blend"])
        extra["blend"] = float(conf["blend"])
        log.info("best.pt: %.2f x the fine-tuned weights + %.2f x %s (blend)", conf["blend"], 1 - conf["blend"], init)
    white = None
    if conf["whitening_dim"] and len(data) >= MIN_FIT_CODES:
        codes = encode_images(model.encoder.to(device).eval(), list(data), prepared=True)
        white = Whitening.fit(codes, conf["whitening_dim"], conf["whitening_shrink"])
        log.info("whitening: %d-d, fitted on %d codes, saved in %s", white.dim, white.fitted_on, best)
    elif conf["whitening_dim"]:
        log.warning("only %d images: no whitening saved (it needs %d)", len(data), MIN_FIT_CODES)
    still = STILL_COS if init_ckpt is None else checkpoint_still_cos(init_ckpt, init)
    save_checkpoint(best, model, {**ckpt["conf"], "still_cos": still}, whitening=white, **extra)
    return white


def _plot_history(history: list[dict[str, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    epochs = [h["epoch"] for h in history]
    ax.plot(epochs, [h["train_loss"] for h in history], label="train")
    ax.plot(epochs, [h["val_loss"] for h in history], label="validation")
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss: reconstruction + contrastive x place term")
    ax.set_title("CAE training")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(images: str | Path | Sequence[str | Path], out: str | Path = "runs/train", conf: dict[str, Any] | None = None,
         restart: bool = False) -> dict[str, Any]:
    """Trains the autoencoder.

    Args:
        images: a folder, or several, searched recursively for images.
        out: run folder; ``last.pt`` there is resumed unless ``restart``.
        conf: overrides of ``default_conf`` (checked against ``conf_rules`` before anything is written).
        restart: ignore an existing ``last.pt`` (it is overwritten at the end of the first epoch).

    Returns:
        Summary dict: ``best_val_loss``, ``best_epoch``, ``epochs_run``, ``first_val_loss``, ``best`` (path of
        ``best.pt``), ``history``, ``images`` (how many were used), ``unreadable`` (how many were skipped) and
        ``skipped`` (their paths).

    Raises:
        ConfigError: a bad conf key or value, an unavailable device, a bad ``out``, a missing or empty image folder,
            fewer than 2 readable images, a damaged ``last.pt``, or a diverged training.
        DatabaseError: a result file cannot be written.
    """
    conf, device, folders, files = _prepare(images, Path(out), conf)
    data, used = load_image_folder(files, conf["lowpass"])
    if conf["threads"]:
        torch.set_num_threads(conf["threads"])
    train_set, val_set, split = _split(_Frames(data, *sequence_order(used)), used, conf)
    out = prepare_out_dir(out)
    teacher = _teacher(conf, device)
    model, optim, progress = _resume_or_start(out / "last.pt", conf, device, val_set, restart, teacher)
    write_text_atomic(out / "split.json", json.dumps(split, indent=1))
    dump_conf({**conf, "images": folders}, out / "conf.yaml")
    kept = set(used)
    skipped = [str(p) for p in files if p not in kept]
    log.info("training on %d images, validating on %d (%d unreadable skipped), device %s", len(train_set),
             len(val_set), len(skipped), device)
    progress = _fit(model, optim, train_set, val_set, conf, device, out, progress, teacher)
    if not (out / "best.pt").is_file():
        raise ConfigError(f"{out / 'best.pt'} is missing (deleted after an earlier run?); run with --restart")
    white = _finish_best(out / "best.pt", data, conf, device)
    summary = {"best_val_loss": progress.best_val, "best_epoch": progress.best_epoch,
               "epochs_run": len(progress.history) - 1, "first_val_loss": progress.history[0]["val_loss"],
               "best": str(out / "best.pt"), "history": progress.history, "images": len(used),
               "unreadable": len(skipped), "skipped": skipped,
               "whitening": None if white is None else {"dim": white.dim, "fitted_on": white.fitted_on}}
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=1))
    return summary
