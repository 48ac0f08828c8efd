"""Evaluation plots (PNG, matplotlib's Agg canvas; no pyplot, so no global state and no display needed).

- ``plot_pr_curve``: precision-recall curve of a swept score, with the operating point and max recall at 100 %.
- ``plot_trajectory``: the x-z trajectory with true loops, correct detections (green) and false ones (red).
- ``plot_similarity``: the code cosine-similarity matrix beside the ground-truth pairs (one side of the diagonal,
  where the detections are drawn: ``ground_truth_panel``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure

from cae.encode import normalize_codes

from .ground_truth import pair_matrix
from .metrics import PRCurve, PRResult

__all__ = ["plot_pr_curve", "plot_trajectory", "plot_similarity", "ground_truth_panel"]

GT_COLOUR, TP_COLOUR, FP_COLOUR = "tab:blue", "tab:green", "tab:red"
_MAX_MATRIX = 1500  # larger similarity matrices are shown subsampled


def _save(fig: Figure, path: Path) -> Path:
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=110)
    return path


def plot_pr_curve(curve: PRCurve, path: str | Path, score: str = "inliers", operating: PRResult | None = None,
                  title: str = "") -> Path:
    """Precision (y) against recall (x) over the swept ``score``, one point per threshold.

    Args:
        curve: from ``pr_curve``; an empty curve draws an annotated empty plot.
        path: PNG to write.
        score: name of the swept score (legend and title).
        operating: the detector's accepted loops, drawn as a star.
        title: first title line (e.g. the run name).

    Returns:
        ``path``.
    """
    fig = Figure(figsize=(6.4, 5.2))
    ax = fig.add_subplot()
    r100, t100 = curve.max_recall_at_precision_1()
    ap = curve.average_precision()
    if len(curve.thresholds) and curve.positives:
        r = np.concatenate([[0.0], curve.recall])
        p = np.concatenate([[curve.precision[0]], curve.precision])
        ax.step(r, p, where="pre", color="tab:blue", lw=1.8, label=f"sweep {score} (AP = {ap:.3f})")
        ax.plot(curve.recall, curve.precision, ".", color="tab:blue", ms=4)
        if t100 is not None:
            ax.plot([r100], [1.0], "o", mfc="none", mec="black", ms=10,
                    label=f"max recall @ 100 % precision = {r100:.3f} ({score} >= {t100:g})")
    else:
        ax.text(0.5, 0.5, "no detection or no true loop:\nnothing to sweep", ha="center", va="center",
                transform=ax.transAxes)
    if operating is not None and operating.recall is not None and not np.isnan(operating.recall):
        ax.plot([operating.recall], [operating.precision], "*", color="tab:orange", ms=14,
                label=f"operating point (P {operating.precision:.3f}, R {operating.recall:.3f})")
    ax.set(xlim=(-0.02, 1.02), ylim=(-0.02, 1.05), xlabel="recall (queries with a correct loop / queries with a loop)",
           ylabel="precision (correct / detected)")
    ax.set_title(f"{title}\nprecision-recall, per query, sweeping {score}".strip(), fontsize=10)
    ax.grid(alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    return _save(fig, Path(path))


def plot_trajectory(poses: np.ndarray, path: str | Path, gt_pairs: np.ndarray, detections: np.ndarray,
                    correct: np.ndarray, title: str = "", up: int = 1) -> Path:
    """The ground track (the plane across the gravity axis ``up``: x-z for KITTI's y, x-y for a z-up world) with
    loops drawn as segments between the two frames' positions.

    Args:
        poses: ``(N, 3, 4)`` camera-to-world poses, row = frame id (NaN rows for unknown frames are skipped).
        path: PNG to write.
        gt_pairs: ``(P, 2)`` true loop pairs (blue); their queries are ringed.
        detections: ``(L, 2)`` accepted ``(query, match)`` loops.
        correct: ``(L,)`` bool, True where the detection is a true pair (green), else red with a cross.
        title: first title line.

    Returns:
        ``path``.
    """
    poses = np.asarray(poses, np.float64).reshape(-1, 3, 4)
    plane = [a for a in range(3) if a != up]
    xz = poses[:, plane, 3]
    n = len(xz)
    fig = Figure(figsize=(7.0, 6.4))
    ax = fig.add_subplot()
    track = xz.copy()
    if n > 2:  # do not draw a jump between passes (or a missing stretch) as driven road
        step = np.linalg.norm(np.diff(xz, axis=0), axis=1)
        jump = np.flatnonzero(step > max(10.0, 10 * np.nanmedian(step)))
        track = np.insert(track, jump + 1, np.nan, axis=0)
    ax.plot(track[:, 0], track[:, 1], "-", color="0.6", lw=1.0, label="trajectory", zorder=1)
    if n:
        ax.plot(*xz[0], "k^", ms=8, label="start", zorder=5)

    def segs(pairs: np.ndarray) -> np.ndarray:
        p = np.asarray(pairs, np.int64).reshape(-1, 2)
        p = p[(p >= 0).all(1) & (p < n).all(1)]
        return np.stack([xz[p[:, 0]], xz[p[:, 1]]], axis=1) if len(p) else np.zeros((0, 2, 2))

    gt = np.asarray(gt_pairs, np.int64).reshape(-1, 2)
    if len(gt):
        ax.add_collection(LineCollection(segs(gt), colors=GT_COLOUR, lw=0.8, alpha=0.35, zorder=2))
        q = np.unique(gt[:, 0])
        q = q[q < n]
        ax.scatter(xz[q, 0], xz[q, 1], s=60, facecolors="none", edgecolors=GT_COLOUR, lw=0.9, zorder=3,
                   label=f"true loop ({len(gt)} pairs, {len(np.unique(gt[:, 0]))} queries)")
    det = np.asarray(detections, np.int64).reshape(-1, 2)
    ok = np.asarray(correct, bool).reshape(-1)
    for mask, colour, marker, name in ((ok, TP_COLOUR, "o", "correct detection"),
                                       (~ok, FP_COLOUR, "x", "false detection")):
        d = det[mask]
        d = d[(d >= 0).all(1) & (d < n).all(1)]
        if len(d):
            ax.add_collection(LineCollection(segs(d), colors=colour, lw=1.6, zorder=4))
            ax.scatter(xz[d[:, 0], 0], xz[d[:, 0], 1], s=16 if marker == "o" else 50, c=colour, marker=marker,
                       zorder=6, label=f"{name} ({len(d)})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel=f"{'xyz'[plane[0]]} (m)", ylabel=f"{'xyz'[plane[1]]} (m)")
    ax.set_title(f"{title}\ntrajectory (x-z) with loops drawn between query and match".strip(), fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return _save(fig, Path(path))


def ground_truth_panel(gt_pairs: np.ndarray, m: int, step: int = 1) -> np.ndarray:
    """The ground-truth panel of ``plot_similarity``: ``(m, m)`` bool, True at (query block, earlier block) for every
    pair, one side of the diagonal only (query down, earlier frame across, where the detections are drawn); a block
    of ``step`` frames is marked when any pair falls in it.

    Args:
        gt_pairs: ``(P, 2)`` true pairs, either order.
        m: blocks a side.
        step: frames a block.
    """
    return np.tril(pair_matrix(np.asarray(gt_pairs, np.int64).reshape(-1, 2) // step, m))


def plot_similarity(codes: np.ndarray, frame_ids: np.ndarray, n_frames: int, gt_pairs: np.ndarray,
                    path: str | Path, detections: np.ndarray | None = None, correct: np.ndarray | None = None,
                    title: str = "") -> Path:
    """Cosine similarity of every pair of keyframe codes beside the ground-truth pair matrix.

    Args:
        codes: ``(n, D)`` keyframe codes (normalised here, so any scale works).
        frame_ids: ``(n,)`` frame id of each code; frames without a code (gated) are left blank.
        n_frames: side of both matrices (frames of the sequence).
        gt_pairs: ``(P, 2)`` true pairs.
        path: PNG to write.
        detections: ``(L, 2)`` accepted loops, marked on the ground-truth panel (green correct, red false).
        correct: ``(L,)`` bool.
        title: first title line.

    Returns:
        ``path``.
    """
    n_frames = int(max(n_frames, 1))
    ids = np.asarray(frame_ids, np.int64).reshape(-1)
    codes = np.asarray(codes, np.float32).reshape(len(ids), -1) if len(ids) else np.zeros((0, 1), np.float32)
    keep = (ids >= 0) & (ids < n_frames)
    ids, codes = ids[keep], codes[keep]
    step = max(1, int(np.ceil(n_frames / _MAX_MATRIX)))
    m = -(-n_frames // step)
    sim = np.full((m, m), np.nan, np.float32)
    if len(ids):
        sub = ids % step == 0
        c = normalize_codes(codes[sub])
        r = ids[sub] // step
        sim[np.ix_(r, r)] = c @ c.T
    gt = ground_truth_panel(gt_pairs, m, step)
    fig = Figure(figsize=(12.0, 5.6))
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    extent = (-0.5, n_frames - 0.5, n_frames - 0.5, -0.5)
    lo = float(np.nanmin(sim)) if np.isfinite(sim).any() else 0.0
    im = ax1.imshow(sim, cmap="viridis", vmin=min(lo, 0.999), vmax=1.0, extent=extent,
                    interpolation="nearest")
    fig.colorbar(im, ax=ax1, fraction=0.046, pad=0.04, label="cosine similarity")
    ax1.set_title("code similarity (cosine, keyframes; blank = gated)" + (f", every {step}th" if step > 1 else ""),
                  fontsize=10)
    ax2.imshow(gt, cmap="Greys", vmin=0, vmax=1, extent=extent, interpolation="nearest")
    ax2.set_title("ground-truth loop pairs (black)", fontsize=10)
    if detections is not None and len(detections):
        det = np.asarray(detections, np.int64).reshape(-1, 2)
        ok = np.ones(len(det), bool) if correct is None else np.asarray(correct, bool)
        for mask, colour, name in ((ok, TP_COLOUR, "correct detection"), (~ok, FP_COLOUR, "false detection")):
            if mask.any():
                ax2.scatter(det[mask, 1], det[mask, 0], s=10, c=colour, label=f"{name} ({mask.sum()})")
        ax2.legend(loc="upper right", fontsize=8)
    for ax in (ax1, ax2):
        ax.set(xlabel="frame index (earlier)", ylabel="frame index (query)")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return _save(fig, Path(path))
