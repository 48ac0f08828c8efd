"""The place term of the training loss: a contrastive (InfoNCE) loss on the code, without labels.

Frames come from folders, each read as one sequence in name order. A pair is two views of one frame, or of a frame
and a temporal neighbour (at most ``neighbours`` frames away in the same folder): the same place. Every other frame
of the batch is a negative, as long as it is at least ``far`` frames away in the same folder (or in another folder);
frames nearer than that are left out of the loss, neither pulled nor pushed. A revisit found in the folder
(``cae.revisits``: a stretch that matches another stretch far away) is a positive too, and never a negative.

Shapes: codes ``(B, D)``; folder ids and positions ``(B,)`` int. Numpy for the sampling, torch for the loss.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["neighbour_partners", "with_revisits", "far_mask", "not_revisits", "info_nce", "code_anchor"]


def neighbour_partners(folder: np.ndarray, position: np.ndarray, picks: np.ndarray, neighbours: int,
                       rng: np.random.Generator) -> np.ndarray:
    """For each picked frame, a random frame of the same folder at most ``neighbours`` positions away (itself when
    it has none in the set).

    Args:
        folder: ``(N,)`` folder id of every frame of the set.
        position: ``(N,)`` position of every frame in its folder (name order).
        picks: ``(B,)`` indices into the set.
        neighbours: the largest position gap of a positive (0: the frame itself).

    Returns:
        ``(B,)`` indices into the set.
    """
    out = np.asarray(picks, np.int64).copy()
    if neighbours <= 0 or len(out) == 0:
        return out
    for k, i in enumerate(out):
        near = np.flatnonzero((folder == folder[i]) & (np.abs(position - position[i]) <= neighbours))
        out[k] = near[rng.integers(len(near))]
    return out


def with_revisits(partners: np.ndarray, picks: np.ndarray, revisits: np.ndarray, share: float,
                  rng: np.random.Generator) -> np.ndarray:
    """Each picked frame that has revisits takes one of them as its partner instead, with probability ``share``.

    Args:
        partners: ``(B,)`` indices into the set (``neighbour_partners``).
        picks: ``(B,)`` indices into the set.
        revisits: ``(M, 2)`` indices into the set, each row one place (``cae.revisits.mine_revisits``).
        share: probability of taking a revisit where there is one.

    Returns:
        ``(B,)`` indices into the set.
    """
    out = np.asarray(partners, np.int64).copy()
    revisits = np.asarray(revisits, np.int64).reshape(-1, 2)
    if len(revisits) == 0 or share <= 0:
        return out
    for k, i in enumerate(np.asarray(picks, np.int64)):
        mine = np.concatenate([revisits[revisits[:, 0] == i, 1], revisits[revisits[:, 1] == i, 0]])
        if len(mine) and rng.random() < share:
            out[k] = mine[rng.integers(len(mine))]
    return out


def not_revisits(picks: np.ndarray, revisits: np.ndarray) -> np.ndarray:
    """``(B, B)`` bool: False where two picked frames are a revisit of each other (never each other's negatives)."""
    picks = np.asarray(picks, np.int64)
    out = np.ones((len(picks), len(picks)), bool)
    revisits = np.asarray(revisits, np.int64).reshape(-1, 2)
    if len(revisits) == 0:
        return out
    at = {int(f): k for k, f in enumerate(picks.tolist())}  # a frame's row in the batch
    for i, j in revisits.tolist():
        if i in at and j in at:
            out[at[i], at[j]] = out[at[j], at[i]] = False
    return out


def far_mask(folder: np.ndarray, position: np.ndarray, far: int) -> np.ndarray:
    """``(B, B)`` bool: True where two frames may be used as each other's negatives (other folder, or at least
    ``far`` positions apart)."""
    folder, position = np.asarray(folder), np.asarray(position)
    return (folder[:, None] != folder[None, :]) | (np.abs(position[:, None] - position[None, :]) >= far)


def info_nce(a: torch.Tensor, b: torch.Tensor, negatives: torch.Tensor, temperature: float) -> torch.Tensor:
    """Symmetric InfoNCE over two views: row ``i`` of ``a`` and of ``b`` are one place.

    The codes are centred on the batch's mean code and L2-normalised first (as the whitening used at retrieval
    removes the mean every code of a camera shares). For each of the ``2B`` codes the positive is its partner; the
    candidates are the partner and the views of every frame ``j`` with ``negatives[i, j]``.

    Args:
        a, b: ``(B, D)`` codes of the two views.
        negatives: ``(B, B)`` bool (``far_mask``).
        temperature: softmax temperature (> 0).

    Returns:
        Scalar loss (0 for an empty batch).
    """
    n = len(a)
    if n == 0:
        return a.sum() * 0.0
    z = torch.cat([a, b])
    z = F.normalize(z - z.mean(0, keepdim=True), dim=1)
    sims = z @ z.T / temperature
    neg = negatives.to(z.device).bool()
    allowed = neg.repeat(2, 2)
    idx = torch.arange(2 * n, device=z.device)
    partner = (idx + n) % (2 * n)
    allowed[idx, partner] = True
    allowed[idx, idx] = False
    logits = sims.masked_fill(~allowed, float("-inf"))
    return F.cross_entropy(logits, partner)


def code_anchor(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """How far codes moved from a reference's: the batch mean of ``1 - cos`` between each student code and the
    teacher's code of the same frame, both centred on the teacher batch's mean code (as ``info_nce`` centres).

    Args:
        student: ``(B, D)`` codes being trained (of a changed view).
        teacher: ``(B, D)`` the reference weights' codes (of the clean frame), without a gradient.

    Returns:
        Scalar loss in [0, 2] (0 for an empty batch).
    """
    if len(student) == 0:
        return student.sum() * 0.0
    mean = teacher.mean(0, keepdim=True)
    return (1.0 - F.cosine_similarity(student - mean, teacher - mean, dim=1)).mean()
