"""Methods side by side on the same frames: the paper's config, the default config, two baselines (thumbnail
cosine, tf-idf bag of visual words) followed by the same verification, and MILD alone and in front of that
verification; and "does the learned code earn its place?" (shipped weights, random weights, a thumbnail and
fine-tuned weights, single frames and the detector, where conditions change)."""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from cae_lcd.core.conf import load_conf_file, merge_conf
from retrieval.descriptors import create_descriptor
from retrieval.detector import resolve_conf
from retrieval.methods import METHODS
from retrieval.sequences import open_sequence

from .common import REPO, Budget, detect_run, ground_truth_pairs, md_table, run_metrics

__all__ = ["slug", "method_confs", "method_metrics", "run_methods", "false_loops", "methods_table",
           "StudySet", "image_codes", "frame_codes", "single_frame_retrieval", "fine_tune", "training_study",
           "training_table"]

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


@dataclass(frozen=True)
class StudySet:
    """One set of the training study: a first traversal, then a second under changed conditions."""

    name: str  #: as the table names it
    folder: Path  #: the sequence (KITTI layout or a plain folder), first traversal then second
    n_first: int  #: frames of the first traversal; the rest are the queries
    truth: np.ndarray  #: ``(P, 2)`` true pairs
    tune: Path | None = None  #: unlabeled images the fine-tuned row adapts the shipped weights to (None: no such row)


def image_codes(images: Sequence[np.ndarray], descriptor: Any) -> np.ndarray:
    """``(N, dim)`` float32 codes of images with a ``retrieval.descriptors`` descriptor (batched when it can)."""
    if not len(images):
        return np.empty((0, descriptor.dim), np.float32)
    images = list(images)
    codes = descriptor.encode_batch(images) if descriptor.encodes_in_batches else [descriptor(im) for im in images]
    return np.stack(codes).reshape(len(images), -1).astype(np.float32)


def frame_codes(frames: Sequence[Path], descriptor: Any, batch: int = 32) -> np.ndarray:
    """``(N, dim)`` float32 codes of image files with a ``retrieval.descriptors`` descriptor (batched when it can),
    ``batch`` files read at a time."""
    from cae_lcd.core.images import read_image

    out = [np.empty((0, descriptor.dim), np.float32)]
    for i in range(0, len(frames), batch):
        out.append(image_codes([read_image(p) for p in frames[i:i + batch]], descriptor))
    return np.concatenate(out)


def single_frame_retrieval(codes: np.ndarray, n_first: int, truth: np.ndarray, ks: tuple[int, ...] = (1, 10),
                           exclude_recent: int = 50) -> dict[int, float]:
    """Recall@k of the second traversal's frames, single frames: the codes whitened by a PCA fitted on the
    sequence's own codes (``cae.whitening``, the detector's defaults), cosine, no temporal filter; each query
    searches every frame at least ``exclude_recent`` frames older (the detector's window), so a second-traversal
    frame may also be drawn to the other frames of its own light or season.

    Args:
        codes: ``(N, D)`` codes in sequence order; rows ``>= n_first`` are the queries.
        n_first: length of the first traversal.
        truth: ``(P, 2)`` true pairs (either order); queries without a true pair do not count.
        exclude_recent: frames younger than this are not searched (``search.exclude_recent``).

    Returns:
        ``{k: recall}`` (nan when no query has a true pair).
    """
    from cae.whitening import Whitening

    refs: dict[int, set[int]] = {}
    for a, b in np.asarray(truth, np.int64).reshape(-1, 2).tolist():
        q, r = max(a, b), min(a, b)
        if q >= n_first and r <= q - exclude_recent:
            refs.setdefault(q, set()).add(r)
    if not refs:
        return {k: float("nan") for k in ks}
    x = Whitening.fit(codes).transform(codes)
    hits = {k: 0 for k in ks}
    for q, true in refs.items():
        sims = x[:q - exclude_recent + 1] @ x[q]
        top = np.argsort(-sims, kind="stable")[:max(ks)].tolist()
        for k in ks:
            hits[k] += bool(true & set(top[:k]))
    return {k: hits[k] / len(refs) for k in ks}


def _study_variants(run_dir: Path) -> dict[str, dict[str, Any]]:
    """Descriptor confs of the rows every set has: shipped weights, the reconstruction-only weights they were trained
    from (the paper's objective), the same network at random init (reading its input as the shipped weights do), a
    thumbnail."""
    from cae.model import Encoder
    from cae.weights import (DEFAULT_WEIGHTS, RECONSTRUCTION_WEIGHTS, checkpoint_input_norm, checkpoint_lowpass,
                             load_checkpoint, save_checkpoint)

    torch.manual_seed(0)
    random_ckpt = run_dir / "random_encoder.pt"
    shipped = load_checkpoint(DEFAULT_WEIGHTS)
    reading = checkpoint_input_norm(shipped, DEFAULT_WEIGHTS), checkpoint_lowpass(shipped, DEFAULT_WEIGHTS)
    save_checkpoint(random_ckpt, Encoder(*reading), {"init": "N(0, 0.05), torch.manual_seed(0)"})  # read alike
    return {"shipped weights": {"name": "cae"},
            "reconstruction only (cae_mixed.pt, the paper's objective)": {"name": "cae",
                                                                           "weights": str(RECONSTRUCTION_WEIGHTS)},
            "same network, random init": {"name": "cae", "weights": str(random_ckpt)},
            "thumbnail 64x48": {"name": "thumbnail"}}


def fine_tune(images: Path, out: Path, conf: dict[str, Any] | None = None) -> dict[str, Any]:
    """``cae-lcd train --images IMAGES --init shipped`` (``conf`` on top): the summary plus ``wall_s`` and
    ``s_per_epoch``."""
    import time

    from cae.train import main as train

    t0 = time.perf_counter()
    summary = train(images, out, {"init": "shipped", **(conf or {})}, restart=True)
    epochs = [h["seconds"] for h in summary["history"][1:]]
    return {**summary, "wall_s": time.perf_counter() - t0, "s_per_epoch": float(np.mean(epochs)) if epochs else 0.0}


def training_study(sets: Sequence[StudySet], run_dir: str | Path, tune_conf: dict[str, Any] | None = None,
                   detector: bool = True, override: dict[str, Any] | None = None) -> dict[str, Any]:
    """Does the learned code earn its place? Per set: shipped weights, random init, a 64x48 thumbnail and (where the
    set names ``tune`` images) the shipped weights fine-tuned on them, without labels.

    Args:
        sets: the study's sets.
        run_dir: folder for the random checkpoint, the fine-tuning runs and the detect runs.
        tune_conf: ``cae.train`` overrides of the fine-tuning (``init`` is ``shipped``).
        detector: also run the default detector with each descriptor (precision / recall); False: retrieval only.
        override: detector conf overrides applied to every run.

    Returns:
        ``{"sets": {set: {row: {"r1", "r10", ["precision", "recall", "max_recall_100"]}}}, "tuned": {set: fine-tune
        summary}}``.
    """
    from retrieval.descriptors import create_descriptor

    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    base = _study_variants(run_dir)
    window = int(resolve_conf(merge_conf({}, override, strict=False))["search"]["exclude_recent"])
    res: dict[str, Any] = {"sets": {}, "tuned": {}}
    for n, st in enumerate(sets):
        rows = dict(base)
        if st.tune is not None:
            tuned = fine_tune(st.tune, run_dir / f"tuned_{n}", tune_conf)
            res["tuned"][st.name] = {k: tuned[k] for k in ("wall_s", "s_per_epoch", "epochs_run", "images", "best")}
            rows[f"fine-tuned on {st.tune.name} (unlabeled)"] = {"name": "cae", "weights": tuned["best"]}
        frames = list(open_sequence(st.folder).frames)
        res["sets"][st.name] = {}
        for i, (label, desc) in enumerate(rows.items()):
            rk = single_frame_retrieval(frame_codes(frames, create_descriptor(desc)), st.n_first, st.truth,
                                        exclude_recent=window)
            row: dict[str, Any] = {"r1": rk[1], "r10": rk[10]}
            if detector:
                conf = merge_conf({"descriptor": desc}, override, strict=False)
                summary = detect_run(st.folder, run_dir / f"set{n}_row{i}", conf)
                m = method_metrics(summary["out"], conf, st.truth)
                row.update(precision=m["precision"], recall=m["recall"], max_recall_100=m["r100"])
            log.info("%s, %s: %s", st.name, label, row)
            res["sets"][st.name][label] = row
    return res


def training_table(res: dict[str, Any]) -> str:
    """Markdown: one row per set and descriptor."""
    rows = []
    for name, by_row in res["sets"].items():
        for label, r in by_row.items():
            det = "not run" if "precision" not in r else \
                f"{r['precision']:.3f} / {r['recall']:.3f} / {r['max_recall_100']:.3f}"
            rows.append([name, label, f"{r['r1']:.3f} / {r['r10']:.3f}", det])
    return md_table(["set", "code", "single frame Recall@1 / @10", "detector precision / recall / max recall @ 100% P"],
                    rows)
