"""Descriptor matching: nearest neighbour with Lowe's ratio test, optional mutual check.

numpy in, numpy out. ``match_ratio_many`` is the fast path used per frame (GEMM blocks, in-place distance
expansion); ``match_ratio`` is the brute-force reference (one pair, plain numpy) it is tested against.

Returned matches are ``(M, 2)`` int64 arrays of ``(query_index, candidate_index)``; ``(0, 2)`` when nothing matches.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

__all__ = ["pairwise_sq_l2", "pairwise_hamming", "match_ratio", "match_ratio_many", "EMPTY_MATCHES"]

EMPTY_MATCHES = np.zeros((0, 2), np.int64)


def pairwise_sq_l2(xq: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Squared L2 distances ``(Nq, D), (Nb, D) -> (Nq, Nb)`` float32 (one GEMM)."""
    xq = np.asarray(xq, np.float32)
    xb = np.asarray(xb, np.float32)
    d = (xq * xq).sum(1)[:, None] + (xb * xb).sum(1)[None, :] - 2.0 * (xq @ xb.T)
    return np.maximum(d, 0.0, out=d)


def pairwise_hamming(xq: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Hamming distances of packed binary descriptors ``(Nq, B), (Nb, B) uint8 -> (Nq, Nb)`` float32."""
    bits = np.unpackbits(np.asarray(xq, np.uint8), axis=1).astype(np.float32)
    bitsb = np.unpackbits(np.asarray(xb, np.uint8), axis=1).astype(np.float32)
    d = bits.sum(1)[:, None] + bitsb.sum(1)[None, :] - 2.0 * (bits @ bitsb.T)
    return np.maximum(d, 0.0, out=d)


def _ratio_from_distances(d: np.ndarray, ratio: float, mutual: bool, squared: bool) -> np.ndarray:
    """Ratio test on one ``(Nq, Nb)`` distance block (the block is modified in place)."""
    nq, nb = d.shape
    if nq == 0 or nb == 0:
        return EMPTY_MATCHES
    rows = np.arange(nq)
    nn1 = d.argmin(axis=1)
    best = d[rows, nn1].copy()
    if mutual:
        keep = d.argmin(axis=0)[nn1] == rows
    else:
        keep = np.ones(nq, bool)
    if nb > 1:  # with one candidate feature there is no second neighbour and the ratio test cannot reject
        d[rows, nn1] = np.inf
        second = d.min(axis=1)
        keep &= best < (ratio * ratio if squared else ratio) * second
    q = rows[keep]
    return np.stack([q, nn1[keep]], axis=1).astype(np.int64) if len(q) else EMPTY_MATCHES


def match_ratio(xq: np.ndarray, xb: np.ndarray, ratio: float = 0.8, mutual: bool = False,
                metric: str = "l2") -> np.ndarray:
    """Matches one pair of descriptor sets (brute force).

    Args:
        xq: ``(Nq, D)`` query descriptors (float for ``l2``, packed uint8 for ``hamming``).
        xb: ``(Nb, D)`` candidate descriptors.
        ratio: keep a match when ``dist(1st) < ratio * dist(2nd)`` (Lowe: 0.8).
        mutual: also require the query feature to be the candidate feature's nearest neighbour.
        metric: ``"l2"`` or ``"hamming"``.

    Returns:
        ``(M, 2)`` int64 ``(query_index, candidate_index)``.
    """
    if metric not in ("l2", "hamming"):
        raise ValueError(f"unknown descriptor metric {metric!r}; expected 'l2' or 'hamming'")
    if len(xq) == 0 or len(xb) == 0:
        return EMPTY_MATCHES
    if metric == "hamming":
        return _ratio_from_distances(pairwise_hamming(xq, xb), ratio, mutual, squared=False)
    return _ratio_from_distances(pairwise_sq_l2(xq, xb), ratio, mutual, squared=True)


def match_ratio_many(xq: np.ndarray, xbs: Sequence[np.ndarray], ratio: float = 0.8, mutual: bool = False,
                     metric: str = "l2") -> list[np.ndarray]:
    """Matches one query against several candidates (the per-frame fast path).

    Same result as ``[match_ratio(xq, xb, ...) for xb in xbs]``: one fused GEMM per candidate (torch) instead of
    several full-size numpy temporaries.

    Returns:
        One ``(M_i, 2)`` int64 array per candidate.
    """
    if len(xq) == 0 or sum(len(xb) for xb in xbs) == 0:
        return [EMPTY_MATCHES for _ in xbs]
    if metric == "hamming":
        return [match_ratio(xq, xb, ratio, mutual, metric) for xb in xbs]
    # The GEMM runs in torch, whose thread pool the encoder already uses: numpy's OpenBLAS threads would spin
    # against it on a small machine (measured 8x slower on 2 cores).
    q = torch.from_numpy(np.ascontiguousarray(xq, np.float32))
    qn = (q * q).sum(1, keepdim=True)
    out = []
    for xb in xbs:
        if len(xb) == 0:
            out.append(EMPTY_MATCHES)
            continue
        b = torch.from_numpy(np.ascontiguousarray(xb)).float()
        # squared distances |q|^2 + |b|^2 - 2 q.b in one fused GEMM on a cache-sized block
        d = torch.addmm((b * b).sum(1)[None, :], q, b.T, alpha=-2.0).add_(qn).clamp_(min=0.0)
        out.append(_ratio_from_distances(d.numpy(), ratio, mutual, squared=True))
    return out
