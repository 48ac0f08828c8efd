"""``cae-lcd train --images DIR``: ``cae.train.main`` (also ``python train.py --images DIR``)."""

from __future__ import annotations

import logging
from typing import Any

from cae import train as training
from cae_lcd.core.cli import api_defaults
from cae_lcd.core.conf import load_conf_file

__all__ = ["add_parser", "run", "log_summary"]

log = logging.getLogger("cae_lcd.train")


def add_parser(sub: Any) -> None:
    defaults = api_defaults(training.main)
    p = sub.add_parser("train", help="train the autoencoder on your own images",
                       description="Train the convolutional autoencoder on folders of images; an existing "
                                   "OUT/last.pt is resumed unless --restart.")
    p.add_argument("--images", required=True, nargs="+", help="folder(s) of images, searched recursively")
    p.add_argument("--config", help="YAML file of overrides (e.g. configs/train.yaml)")
    p.add_argument("--out", default=str(defaults["out"]),
                   help="run folder; its last.pt is resumed (default: %(default)s)")
    p.add_argument("--epochs", type=int, help="override conf 'epochs'")
    p.add_argument("--device", help="override conf 'device' (auto, cpu, cuda, cuda:N)")
    p.add_argument("--init", help="override conf 'init': start from 'shipped' (fine-tune the package's weights on "
                                  "your images) or a checkpoint path")
    p.add_argument("--restart", action="store_true", help="do not resume from OUT/last.pt")
    p.set_defaults(func=run)


def log_summary(s: dict[str, Any]) -> None:
    """The end-of-run report."""
    log.info("validation loss %.5f -> %.5f (best at epoch %d of %d); weights: %s", s["first_val_loss"],
             s["best_val_loss"], s["best_epoch"], s["epochs_run"], s["best"])
    if s.get("unreadable"):
        log.warning("%d unreadable image(s) skipped (listed in summary.json)", s["unreadable"])


def run(args: Any) -> None:
    conf = load_conf_file(args.config) if args.config else {}
    if args.epochs is not None:
        conf["epochs"] = args.epochs
    if args.device is not None:
        conf["device"] = args.device
    if args.init is not None:
        conf["init"] = args.init
    log_summary(training.main(args.images, args.out, conf, restart=args.restart))
