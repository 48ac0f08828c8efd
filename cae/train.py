"""Training the autoencoder on a folder of images (``python train.py --images DIR``).

Seeded 70/30 train/validation split, sigmoid cross-entropy on the logits, Adam, mini-batches of 32, validation loss
each epoch, best-validation weights kept (``best.pt``, loadable by ``cae.load_encoder``), resumable from ``last.pt``,
the resolved conf saved as ``conf.yaml`` and the loss curves as ``loss.png``.

The paper trained for 5000 epochs on a GPU. The CPU-sane default here is 40 epochs with early stopping (patience 8):
on the 360 KITTI frames that is about 25 minutes on 2 cores and reaches most of the validation-loss drop.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .cli import run_cli
from .conf import ConfigError, dump_conf, load_conf_file, merge_conf
from .model import INPUT_SIZE, ConvAutoencoder
from .preprocess import IMAGE_EXTENSIONS, ImageError, read_image, to_network_u8
from .weights import load_checkpoint, resolve_device, save_checkpoint

__all__ = ["default_conf", "list_images", "load_image_folder", "main"]

log = logging.getLogger(__name__)

default_conf: dict[str, Any] = {
    "epochs": 40,  # maximum number of epochs (the paper: 5000 on a GPU)
    "batch_size": 32,  # mini-batch size (paper: 32)
    "lr": 1.0e-3,  # Adam learning rate (paper: 1e-3)
    "val_fraction": 0.3,  # share of images held out for validation (paper: 30%)
    "seed": 0,  # seeds the split, the initialisation and the batch order
    "patience": 8,  # stop after this many epochs without a better validation loss; 0 = never stop early
    "min_delta": 1.0e-5,  # an improvement smaller than this does not count for early stopping
    "device": "auto",  # "auto" (CUDA if present), "cpu", "cuda", "cuda:1", ...
    "max_images": None,  # use at most this many images (a seeded random subset); None = all
}


def list_images(folder: str | Path) -> list[Path]:
    """All image files below ``folder`` (recursive), sorted by path.

    Raises:
        ConfigError: the folder is missing or holds no image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(f"image folder not found: {folder}")
    files = sorted(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())
    if not files:
        raise ConfigError(f"no images ({', '.join(IMAGE_EXTENSIONS)}) found below {folder}")
    return files


def load_image_folder(files: Sequence[Path]) -> tuple[np.ndarray, list[Path]]:
    """Reads and resizes images to the network size; unreadable ones are skipped with a warning.

    Returns:
        ``(N, 256, 256, 3)`` uint8 RGB array and the paths actually used.
    """
    arrays, used = [], []
    for path in tqdm(files, desc="loading images", unit="img", leave=False):
        try:
            arrays.append(to_network_u8(read_image(path), INPUT_SIZE))
            used.append(path)
        except ImageError as err:
            log.warning("skipping %s", err)
    if not arrays:
        raise ConfigError("none of the images could be read")
    return np.stack(arrays), used


def _to_batch(images: np.ndarray, device: torch.device) -> torch.Tensor:
    x = torch.from_numpy(images).to(device).permute(0, 3, 1, 2).float().div_(255.0)
    return x.contiguous(memory_format=torch.channels_last)


def _evaluate(model: ConvAutoencoder, images: np.ndarray, batch_size: int, device: torch.device) -> float:
    model.eval()
    total = 0.0
    with torch.inference_mode():
        for start in range(0, len(images), batch_size):
            x = _to_batch(images[start:start + batch_size], device)
            total += F.binary_cross_entropy_with_logits(model(x), x, reduction="sum").item() / x[0].numel()
    return total / max(1, len(images))


def _plot_history(history: list[dict[str, float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    epochs = [h["epoch"] for h in history]
    ax.plot(epochs, [h["train_loss"] for h in history], label="train")
    ax.plot(epochs, [h["val_loss"] for h in history], label="validation")
    ax.set_xlabel("epoch")
    ax.set_ylabel("sigmoid cross-entropy per pixel")
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
        conf: overrides of ``default_conf``.
        restart: ignore an existing ``last.pt`` (it is overwritten at the end of the first epoch).

    Returns:
        Summary dict: ``best_val_loss``, ``best_epoch``, ``epochs_run``, ``first_val_loss``, ``best``, ``history``.
    """
    conf = merge_conf(default_conf, conf)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    device = resolve_device(conf["device"])
    folders = [images] if isinstance(images, (str, Path)) else list(images)
    files = [f for folder in folders for f in list_images(folder)]
    rng = np.random.default_rng(conf["seed"])
    if conf["max_images"] and len(files) > conf["max_images"]:
        files = sorted(rng.choice(np.array(files, dtype=object), conf["max_images"], replace=False).tolist())
    data, files = load_image_folder(files)
    if len(data) < 2:
        raise ConfigError(f"need at least 2 readable images to train with a validation split; found {len(data)}")
    order = np.random.default_rng(conf["seed"]).permutation(len(data))
    n_val = min(len(data) - 1, max(1, int(round(conf["val_fraction"] * len(data)))))
    val_idx, train_idx = order[:n_val], order[n_val:]
    train_set, val_set = data[np.sort(train_idx)], data[np.sort(val_idx)]
    (out / "split.json").write_text(json.dumps({"train": [str(files[i]) for i in sorted(train_idx)],
                                                "val": [str(files[i]) for i in sorted(val_idx)]}, indent=1))
    dump_conf({**conf, "images": [str(f) for f in folders]}, out / "conf.yaml")
    log.info("training on %d images, validating on %d, device %s", len(train_set), len(val_set), device)

    torch.manual_seed(conf["seed"])
    model = ConvAutoencoder().to(device, memory_format=torch.channels_last)
    optim = torch.optim.Adam(model.parameters(), lr=conf["lr"])
    history: list[dict[str, float]] = []
    start_epoch, best_val, best_epoch = 0, float("inf"), -1
    last_path = out / "last.pt"
    if last_path.exists() and not restart:
        state = load_checkpoint(last_path)
        model.load_state_dict(state["state_dict"], strict=True)
        optim.load_state_dict(state["optimizer"])
        start_epoch, best_val, best_epoch = state["epoch"], state["best_val_loss"], state["best_epoch"]
        history = state["history"]
        log.info("resuming from %s after epoch %d (best validation loss %.5f)", last_path, start_epoch, best_val)
    else:
        history.append({"epoch": 0, "train_loss": float("nan"),
                        "val_loss": _evaluate(model, val_set, conf["batch_size"], device), "seconds": 0.0})
        log.info("initial validation loss %.5f", history[0]["val_loss"])

    batch_rng = np.random.default_rng(conf["seed"] + start_epoch)
    bar = tqdm(range(start_epoch, conf["epochs"]), desc="epochs", unit="epoch", initial=start_epoch,
               total=conf["epochs"])
    for epoch in bar:
        t0 = time.perf_counter()
        model.train()
        perm = batch_rng.permutation(len(train_set))
        total = 0.0
        for start in range(0, len(perm), conf["batch_size"]):
            x = _to_batch(train_set[np.sort(perm[start:start + conf["batch_size"]])], device)
            loss = F.binary_cross_entropy_with_logits(model(x), x)
            optim.zero_grad(set_to_none=True)
            loss.backward()
            optim.step()
            total += loss.item() * len(x)
        val = _evaluate(model, val_set, conf["batch_size"], device)
        history.append({"epoch": epoch + 1, "train_loss": total / len(train_set), "val_loss": val,
                        "seconds": time.perf_counter() - t0})
        if val < best_val - conf["min_delta"]:
            best_val, best_epoch = val, epoch + 1
            save_checkpoint(out / "best.pt", model, conf, epoch=epoch + 1, val_loss=val)
        save_checkpoint(last_path, model, conf, epoch=epoch + 1, optimizer=optim.state_dict(), best_val_loss=best_val,
                        best_epoch=best_epoch, history=history)
        _plot_history(history, out / "loss.png")
        bar.set_postfix(train=f"{history[-1]['train_loss']:.4f}", val=f"{val:.4f}", best=f"{best_val:.4f}")
        if conf["patience"] and epoch + 1 - best_epoch >= conf["patience"]:
            log.info("early stop: no better validation loss for %d epochs", conf["patience"])
            break
    summary = {"best_val_loss": best_val, "best_epoch": best_epoch, "epochs_run": len(history) - 1,
               "first_val_loss": history[0]["val_loss"], "best": str(out / "best.pt"), "history": history}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    parser = parser or argparse.ArgumentParser(description="Train the convolutional autoencoder on a folder of images.")
    parser.add_argument("--images", required=True, nargs="+", help="folder(s) of images, searched recursively")
    parser.add_argument("--config", help="YAML file of overrides (e.g. configs/train.yaml)")
    parser.add_argument("--out", default="runs/train", help="run folder (default: %(default)s)")
    parser.add_argument("--epochs", type=int, help="override conf 'epochs'")
    parser.add_argument("--device", help="override conf 'device'")
    parser.add_argument("--restart", action="store_true", help="do not resume from OUT/last.pt")
    return parser


def cli(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)

    def run() -> None:
        conf = load_conf_file(args.config) if args.config else {}
        if args.epochs is not None:
            conf["epochs"] = args.epochs
        if args.device is not None:
            conf["device"] = args.device
        s = main(args.images, args.out, conf, restart=args.restart)
        log.info("validation loss %.5f -> %.5f (best at epoch %d of %d); weights: %s", s["first_val_loss"],
                 s["best_val_loss"], s["best_epoch"], s["epochs_run"], s["best"])

    return run_cli(run)
