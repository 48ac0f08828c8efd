"""Methods side by side on the same frames: the paper's config, the default config, two baselines (thumbnail
cosine, tf-idf bag of visual words) followed by the same verification, and MILD alone and in front of that
verification; and "does training help?" (shipped, random and other-data weights)."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

import numpy as np
import torch

from core.conf import load_conf_file, merge_conf
from retrieval.descriptors import create_descriptor
from retrieval.detector import resolve_conf
from retrieval.methods import METHODS
from retrieval.sequences import open_sequence

from .common import REPO, Budget, detect_run, ground_truth_pairs, md_table, run_metrics

__all__ = ["slug", "method_confs", "method_metrics", "run_methods", "false_loops", "methods_table",
           "training_study", "training_table"]

log = logging.getLogger(__name__)


def method_confs(vocabulary: str | Path, override: dict[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """Detector confs by method label: paper, default, thumbnail, bovw, MILD and MILD + verification (each +
    ``override``)."""
    paper_file = REPO / "configs" / "paper.yaml"
    confs: dict[str, dict[str, Any]] = {}
    if paper_file.is_file():
        confs["paper (configs/paper.yaml)"] = load_conf_file(paper_file)
    else:
        log.warning("%s not found: the paper row is left out", paper_file)
    confs["default (CAE)"] = {}
    confs["thumbnail 64x48 + verification"] = {"descriptor": {"name": "thumbnail"}}
    confs["bovw tf-idf + verification"] = {"descriptor": {"name": "bovw", "vocabulary": str(vocabulary)}}
    confs["MILD (--method mild)"] = METHODS["mild"]
    confs["MILD + verification (--method mild+verify)"] = METHODS["mild+verify"]
    return {label: merge_conf(c, override, strict=False) for label, c in confs.items()}


def slug(label: str) -> str:
    """A folder name for a method label (``"paper (configs/paper.yaml)"`` -> ``"paper"``)."""
    return re.sub(r"[^a-z0-9]+", "_", label.lower().split(" (")[0]).strip("_")[:40] or "method"


def method_metrics(out: str | Path, conf: dict[str, Any], ground_truth: np.ndarray | None) -> dict[str, Any]:
    """``run_metrics`` with the run's own ``min_matches``; swept on what the run's acceptance rule thresholds: the
    confidence when calibrated or when the policy does not verify (MILD: the posterior), else inliers (cosine when
    geometry is off)."""
    resolved = resolve_conf(conf)
    verify = resolved["policy"]["verify"] or resolved["calibration"]["enabled"]
    score = "confidence" if resolved["calibration"]["enabled"] or not verify else \
        "cosine" if resolved["geometry"]["model"] == "none" else "inliers"
    return run_metrics(out, ground_truth, resolved["policy"]["min_matches"] if verify else 0, score)


def run_methods(sequence: str | Path, run_dir: str | Path, confs: dict[str, dict[str, Any]],
                done: dict[str, dict[str, Any]] | None = None) -> dict[str, dict[str, Any]]:
    """Runs each method over ``sequence`` (skipping those in ``done``: label -> existing run folder's summary).

    Returns:
        label -> metrics (``run_metrics``) plus ``dim``, ``wall_s`` and ``out``.
    """
    truth = ground_truth_pairs(sequence)
    res = {}
    for label, conf in confs.items():
        out = Path(run_dir) / slug(label)
        summary = (done or {}).get(label)
        if summary is None:
            log.info("method %s on %s", label, Path(sequence).name)
            summary = detect_run(sequence, out, conf)
        out = Path(summary["out"])
        res[label] = {**method_metrics(out, conf, truth), "wall_s": summary["wall_s"], "out": str(out),
                      "frames": summary["frames"]}
    return res


def false_loops(sequences: dict[str, str | Path], run_dir: str | Path, confs: dict[str, dict[str, Any]],
                ms_per_frame: dict[str, float], budget: Budget) -> dict[tuple[str, str], int | str]:
    """Loops reported on sequences without any revisit (all false), per (method, sequence), while time allows.

    ``ms_per_frame`` (label -> measured median) estimates each run; a run that would not fit is marked
    ``"not run (time)"``.
    """
    out: dict[tuple[str, str], int | str] = {}
    for name, path in sequences.items():
        n = len(open_sequence(path))
        for label, conf in confs.items():
            est = 1.3 * ms_per_frame.get(label, 500.0) * n / 1e3 + 5.0
            if not budget.allows(est):
                out[(label, name)] = "not run (time)"
                continue
            summary = detect_run(path, Path(run_dir) / name / slug(label), conf)
            out[(label, name)] = int(summary["loops"])
    return out


def _dim(conf: dict[str, Any]) -> str:
    return create_descriptor(resolve_conf(conf)["descriptor"]).size_text()


def methods_table(res: dict[str, dict[str, Any]], confs: dict[str, dict[str, Any]],
                  fl: dict[tuple[str, str], int | str] | None = None, fl_names: tuple[str, ...] = ()) -> str:
    """Markdown: one row per method."""
    rows = []
    for label, r in res.items():
        rk = r.get("recall_at_k", {})
        r100 = "n/a" if r.get("r100") is None else f"{r['r100']:.3f}" + (" (cosine)" if r["score"] == "cosine" else "")
        row = [label, _dim(confs[label]), f"{r['precision']:.3f} ({r['true_positives']}/{r['detections']})",
               "n/a" if r.get("recall") is None else f"{r['recall']:.3f}", r100,
               " / ".join(f"{rk.get(k, float('nan')):.2f}" for k in (1, 5, 10)), f"{r['ms_total']:.0f}"]
        row += [str((fl or {}).get((label, s), "not run")) for s in fl_names]
        rows.append(row)
    header = ["method", "dim", "precision (TP/detections)", "recall", "max recall @ 100% P", "Recall@1/5/10",
              "ms/frame (median)"] + [f"false loops on {s}" for s in fl_names]
    return md_table(header, rows)


def training_study(sequence: str | Path, train_images: str | Path, run_dir: str | Path, epochs: int = 5,
                   max_images: int | None = None, override: dict[str, Any] | None = None,
                   augment: float = 0.4) -> dict[str, dict[str, Any]]:
    """Single-frame Recall@1, the run's Recall@k and max recall at 100 % precision with the shipped weights, random
    weights, and weights trained on ``train_images`` (reconstruction only, and with photometric augmentation).

    Args:
        sequence: evaluated sequence (with ground truth), e.g. Nordland (summer then winter).
        train_images: images for the trained weights, e.g. Nordland's summer half only (no labels).
        run_dir: folder for the checkpoints, the training runs and the detect runs.
        epochs: training epochs of each trained variant.
        max_images: train on at most this many images (None = all).
        override: detector conf overrides applied to every run.
        augment: ``cae.train`` ``augment`` strength of the augmented variant.
    """
    from cae.model import Encoder
    from cae.weights import save_checkpoint

    run_dir = Path(run_dir)
    torch.manual_seed(0)
    random_ckpt = run_dir / "random_encoder.pt"
    save_checkpoint(random_ckpt, Encoder(), {"init": "N(0, 0.05), torch.manual_seed(0)"})
    variants = {"shipped weights (cae/weights)": (None, ""), "random init (seed 0, untrained)": (str(random_ckpt), "")}
    for label, strength in (("reconstruction only", 0.0), (f"augmented {augment:g}", augment)):
        variants.update(_trained_variant(train_images, run_dir / f"train_{strength:g}", epochs, max_images, label,
                                         strength))
    truth = ground_truth_pairs(sequence)
    res = {}
    for i, (label, (weights, note)) in enumerate(variants.items()):
        conf = merge_conf({"descriptor": {"weights": weights}} if weights else {}, override, strict=False)
        summary = detect_run(sequence, run_dir / f"w{i}", conf)
        res[label] = {**method_metrics(summary["out"], conf, truth), "note": note,
                      "single_frame_r1": single_frame_recall(summary["out"], truth)}
    return res


def _trained_variant(images: str | Path, out: Path, epochs: int, max_images: int | None, label: str,
                     augment: float) -> dict[str, tuple[str, str]]:
    import time

    from cae.train import main as train

    t0 = time.perf_counter()
    trained = train(images, out, {"epochs": epochs, "max_images": max_images, "patience": 0, "augment": augment},
                    restart=True)
    note = (f"val loss {trained['first_val_loss']:.4f} -> {trained['best_val_loss']:.4f}, "
            f"{time.perf_counter() - t0:.0f} s")
    return {f"trained on {Path(images).name}, {label}, {trained['epochs_run']} epochs": (trained["best"], note)}


def single_frame_recall(run: str | Path, truth: np.ndarray) -> float:
    """Recall@1 of the whitened single-frame codes of a run (cosine ranking, exclusion window as in the run)."""
    from core.conf import load_conf_file
    from evaluation.metrics import recall_at_k
    from retrieval.database import KeyframeDatabase
    from retrieval.run_folder import RunFolder

    folder = RunFolder(Path(run))
    window = int(load_conf_file(folder.conf)["search"]["exclude_recent"])
    with KeyframeDatabase(folder.database, mode="r") as db:
        x, ids = db.codes()  # the searched codes: already whitened as the run searched them
    sims = x @ x.T
    rows = []
    for i, q in enumerate(ids):
        ok = np.flatnonzero(ids <= q - window)
        if len(ok):
            j = ok[np.argmax(sims[i, ok])]
            rows.append((q, ids[j], sims[i, j], 0, 0, sims[i, j], 0, 0))
    return recall_at_k(np.array(rows, np.float64).reshape(-1, 8), truth, (1,))[1]


def training_table(res: dict[str, dict[str, Any]]) -> str:
    """Markdown: one row per weights variant."""
    rows = []
    for label, r in res.items():
        rk = r["recall_at_k"]
        rows.append([label, f"{r['single_frame_r1']:.3f}", f"{rk[1]:.3f}", f"{r['r100']:.3f}",
                     f"{r['precision']:.3f} / {r['recall']:.3f}", f"{r['ms_total']:.1f}", r["note"]])
    return md_table(["weights", "Recall@1 single frame (whitened)", "Recall@1 (+ temporal)",
                     "max recall @ 100% P", "precision / recall (calibrated)", "ms/frame", "notes"], rows)
