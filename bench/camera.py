"""Any camera, any season: what each stage adds, on data of four cameras, side by side in one run:
``python -m bench.camera [--data ../shared/datasets] [--out BENCHMARKS.md]``.

Rows: the paper's raw 4096-d cosine; the code whitened on the sequence; + the temporal filter; + local
verification (the default). Columns: retrieval Recall@1 (the run's ranking; single frames for the first two rows),
max recall at 100 % precision (sweep on the calibrated confidence), precision / recall at the calibrated operating
point, median ms/frame. Every row is calibrated on its own sequence, as ``cae-lcd detect`` does. Also: loops on
KITTI 00 and 07 (no revisit) with the default. The bundled sample is shrunk to 160x120 and 64x32 into the run
folder (``shrunk_sample``).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path
from typing import Any

import cv2

from cae_lcd.core.images import read_image
from retrieval.detect import SAMPLE_DIR

from .common import REPO, detect_run, ground_truth_pairs, md_table
from .methods import method_metrics
from .run import write_section

__all__ = ["STEPS", "shrunk_sample", "main"]

log = logging.getLogger(__name__)

STEPS: dict[str, dict[str, Any]] = {  #: row label -> detector conf overrides
    "raw code (paper: 4096-d cosine)": {"whitening": {"enabled": False}, "temporal": {"name": "none"},
                                        "calibration": {"verification": "off"}},
    "normalised code (whitened on the sequence)": {"temporal": {"name": "none"},
                                                   "calibration": {"verification": "off"}},
    "+ temporal consistency": {"calibration": {"verification": "off"}},
    "+ verification (the default)": {},
}


def shrunk_sample(dst: Path, size: tuple[int, int]) -> Path:
    """The bundled sample with every frame resized to ``size`` (w, h) as PNG (no calib: K no longer holds)."""
    if (dst / "image_0").is_dir():
        return dst
    (dst / "image_0").mkdir(parents=True)
    for name in ("times.txt", "poses.txt", "loops.txt"):
        shutil.copyfile(SAMPLE_DIR / name, dst / name)
    for src in sorted((SAMPLE_DIR / "image_0").glob("*.jpg")):
        small = cv2.resize(read_image(src), size, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(dst / "image_0" / (src.stem + ".png")), small)
    return dst


def _row(label: str, name: str, m: dict[str, Any]) -> list[str]:
    rk = m.get("recall_at_k", {})
    return [name, label, f"{rk.get(1, float('nan')):.3f}", "n/a" if m.get("r100") is None else f"{m['r100']:.3f}",
            f"{m['precision']:.3f} / {m['recall']:.3f}", f"{m['ms_total']:.1f}"]


CHOSEN = ("gate", "codes", "accept")  #: the calibration notes shown per sequence (``summary.json``, default row)


def _chosen(name: str, summary: dict[str, Any]) -> list[str]:
    """A row of what the stream's own calibration chose at the end of a default run: its notes ``CHOSEN``, as
    written."""
    notes = (summary.get("calibration") or {}).get("notes") or []
    said = {key: next((n.split(": ", 1)[1] for n in notes if n.startswith(key + ": ")), "n/a") for key in CHOSEN}
    return [name, *(said[key] for key in CHOSEN)]


def main(data: Path, run_dir: Path, out: Path | None, weights: str | None = None) -> dict[str, Any]:
    """Runs every step on every sequence; returns the metrics and writes the table into ``out``."""
    sequences = {"KITTI 90 (1241x376)": data / "kitti" / "sequences" / "90",
                 "Nordland summer -> winter (64x32)": data / "nordland",
                 "sample at 160x120": shrunk_sample(run_dir / "sample160", (160, 120)),
                 "sample at 64x32": shrunk_sample(run_dir / "sample64", (64, 32))}
    base = {"descriptor": {"weights": weights}} if weights else {}
    t0 = time.perf_counter()
    rows, res, chosen = [], {}, []
    for name, seq in sequences.items():
        truth = ground_truth_pairs(seq)
        for i, (label, conf) in enumerate(STEPS.items()):
            log.info("%s: %s", name, label)
            run_conf = {**base, **conf}
            summary = detect_run(seq, run_dir / f"{seq.name}_{i}", run_conf)
            res[(name, label)] = m = method_metrics(summary["out"], run_conf, truth)
            rows.append(_row(label, name, m))
            if not conf:  # the default step
                chosen.append(_chosen(name, summary))
    no_loop = {}
    for name in ("00", "07"):
        summary = detect_run(data / "kitti" / "sequences" / name, run_dir / f"noloop_{name}", base)
        no_loop[name] = summary["loops"]
        chosen.append(_chosen(f"KITTI {name} (no revisit)", summary))
    table = md_table(["sequence", "code and stages", "Recall@1", "max recall @ 100% P",
                      "precision / recall (calibrated)", "ms/frame"], rows)
    body = ("### Any camera, any season: what each stage adds (`python -m bench.camera`)\n\n" + table
            + f"\n\nDefault config on KITTI 00 / 07 (no revisit): {no_loop['00']} / {no_loop['07']} loops. "
            f"Weights: {weights or 'shipped'}. Total {time.perf_counter() - t0:.0f} s.\n\n"
            "What the last refit of each default run chose (its `summary.json`, "
            "`calibration.notes`, as written):\n\n" + md_table(["sequence", *CHOSEN], chosen))
    if out is not None:
        write_section(out, body, "camera")
    log.info("\n%s", body)
    return {"rows": res, "no_loop": no_loop}


def _cli() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "datasets")
    ap.add_argument("--run-dir", type=Path, default=Path("runs/bench/camera"))
    ap.add_argument("--out", default=str(REPO / "BENCHMARKS.md"), help="Markdown file to update ('' = none)")
    ap.add_argument("--weights", help="encoder checkpoint (default: the shipped weights)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    main(args.data, args.run_dir, Path(args.out) if args.out else None, args.weights)


if __name__ == "__main__":
    _cli()
