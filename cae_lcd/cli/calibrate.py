"""``cae-lcd calibrate [PATH]``: what the detector will choose for this camera and sequence, and why.

Writes ``calibration.h5`` into ``--out``; a ``cae-lcd detect --lookahead`` with the same ``--out`` uses it (it makes
one itself when the run folder has none; without ``--lookahead``, ``detect`` calibrates on the stream as it goes).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.files import prepare_out_dir
from retrieval import detect
from retrieval.detector import resolve_conf
from retrieval.run_folder import RunFolder
from retrieval.sequences import open_sequence

from .detect import add_sequence_arguments, conf_from_args

__all__ = ["add_parser", "run"]

log = logging.getLogger("cae_lcd.calibrate")


def add_parser(sub: Any) -> None:
    p = sub.add_parser("calibrate", help="choose the gate, normalisation and thresholds for a sequence's camera",
                       description=__doc__.split("\n\n")[0])
    add_sequence_arguments(p)
    p.add_argument("--out", help="run folder to write calibration.h5 into (default: runs/<sequence name>)")
    p.set_defaults(func=run)


def run(args: Any) -> None:
    conf = resolve_conf(conf_from_args(args))
    if not conf["calibration"]["enabled"]:
        why = f", as --method {args.method} sets" if args.method != "cae" else ""
        raise ConfigError(f"this configuration is not calibrated (calibration.enabled: false{why}); nothing to calibrate")
    seq = open_sequence(detect.SAMPLE_DIR if args.path is None else args.path, args.camera, args.topic, args.stride)
    out = Path(args.out) if args.out else detect.default_out(seq)
    cal = detect.calibrate_sequence(seq, conf, progress=not args.no_progress)
    run_folder = RunFolder(prepare_out_dir(out))
    if run_folder.database.exists():
        log.warning("%s already holds a run; its calibration is not replaced: %s written beside it instead",
                    run_folder.root, run_folder.calibration.with_suffix(".new.h5").name)
        cal.save(run_folder.calibration.with_suffix(".new.h5"))
        return
    cal.save(run_folder.calibration)  # what was chosen and why was logged line by line by the calibration
    log.info("wrote %s; run cae-lcd detect with --out %s to use it", run_folder.calibration, run_folder.root)
