"""Descriptor matching: nearest neighbour with Lowe's ratio test, optional mutual check.

numpy in, numpy out. ``match_ratio_many`` is the fast path used per frame (GEMM blocks, in-place distance
expansion; SIFT's descriptors, integers 0-255, in exact 8-bit products where those are faster); ``match_ratio`` is
the brute-force reference (one pair, plain numpy) it is tested against.

Returned matches are ``(M, 2)`` int64 arrays of ``(query_index, candidate_index)``; ``(0, 2)`` when nothing matches.
"""

from __future__ import annotations

import logging
import threading
import time
import weakref
from collections import OrderedDict
from typing import Any, Callable, Sequence

import numpy as np
import torch

__all__ = ["pairwise_sq_l2", "pairwise_hamming", "match_ratio", "match_ratio_many", "ByteForms", "EMPTY_MATCHES",
           "FORMS_KEPT"]

log = logging.getLogger(__name__)

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
    """Ratio test on one ``(Nq, Nb)`` distance block, float32 or the exact int32 squared distances of byte
    descriptors (``_ByteDistances.exact_to``: numpy's integer reductions are several times faster than its float
    ones; compared in float32, which holds those integers exactly). The block is modified in place."""
    nq, nb = d.shape
    if nq == 0 or nb == 0:
        return EMPTY_MATCHES
    rows = np.arange(nq)
    nn1 = d.argmin(axis=1)
    best = d[rows, nn1].astype(np.float32)
    if mutual:
        keep = d.argmin(axis=0)[nn1] == rows
    else:
        keep = np.ones(nq, bool)
    if nb > 1:  # with one candidate feature there is no second neighbour and the ratio test cannot reject
        d[rows, nn1] = np.inf if d.dtype.kind == "f" else np.iinfo(d.dtype).max
        second = d.min(axis=1).astype(np.float32)
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


def _bytes(x: np.ndarray) -> np.ndarray | None:
    """``x`` as uint8 where that is exact (SIFT's descriptors: integers 0-255, float32 or uint8 as stored), else
    None."""
    if x.dtype == np.uint8:
        return x
    if not 0 <= x.min() <= x.max() <= 255:  # NaN fails too
        return None
    u = x.astype(np.uint8)
    return u if np.array_equal(u, x) else None


class _ByteDistances:
    """Squared L2 distances of byte descriptors from 8-bit products (``torch._int_mm``: int8 in, int32 out), the same
    values as the float32 GEMM bit for bit: every term is an integer under 2**24, which float32 holds exactly.

    The bytes are shifted into int8 (``x = s + 128``), so ``|q - b|^2 = -2 s_q.s_b + a_q + c_b`` with the
    per-descriptor terms ``c = |s|^2 + 128^2 D`` (as the candidate) and ``a = c - 2 * 128^2 D`` (as the query)."""

    def __init__(self, x: np.ndarray) -> None:
        self.shifted = torch.from_numpy((x ^ np.uint8(0x80)).view(np.int8))  # x - 128, wrapped into int8
        wide = self.shifted.to(torch.int32)
        self.column = (wide * wide).sum(1, dtype=torch.int32).add_(128 * 128 * x.shape[1])
        self.row = self.column - 2 * 128 * 128 * x.shape[1]

    def exact_to(self, other: "_ByteDistances") -> np.ndarray:
        """``(Nq, Nb)`` int32 squared distances from this set (the query) to ``other`` (the float32 GEMM's values)."""
        d = torch._int_mm(self.shifted, other.shifted.T).mul_(-2)
        return d.add_(self.row[:, None]).add_(other.column[None, :]).numpy()


FORMS_KEPT = 32  #: descriptor sets ``ByteForms`` keeps the 8-bit form of (~70 kB each at 500 SIFT features)


class ByteForms:
    """The 8-bit forms (``_ByteDistances``) of the descriptor sets matched lately, known by the array itself (least
    recently used dropped; thread-safe): a keyframe's descriptors are matched against query after query, and a
    calibration's frames against several others, and each form costs as much to make as a quarter of a pair's
    matching. An array is held by a weak reference (a form is never taken for another array that reuses a dropped
    one's id); descriptors are not modified in place once extracted (``Features``).

    Args:
        keep: forms kept at most.
    """

    def __init__(self, keep: int = FORMS_KEPT) -> None:
        self.keep = int(keep)
        self._forms: OrderedDict[int, tuple[weakref.ref, _ByteDistances | None]] = OrderedDict()
        self._lock = threading.Lock()

    def __call__(self, x: np.ndarray) -> "_ByteDistances | None":
        """The 8-bit form of ``(N, D)`` descriptors, None where they are not bytes (``_bytes``)."""
        key = id(x)
        with self._lock:
            got = self._forms.get(key)
            if got is not None and got[0]() is x:
                self._forms.move_to_end(key)
                return got[1]
        form = _form(x)
        with self._lock:
            self._forms[key] = (weakref.ref(x), form)
            self._forms.move_to_end(key)
            while len(self._forms) > self.keep:
                self._forms.popitem(last=False)
        return form


def _form(x: np.ndarray) -> "_ByteDistances | None":
    """``x``'s 8-bit form, None where it is not bytes."""
    b = _bytes(x)
    return None if b is None else _ByteDistances(b)


_BYTES_FASTER: bool | None = None  #: whether 8-bit products beat float32 here (timed once a process: both exact)


def _bytes_faster() -> bool:
    """Times the two products once a process on SIFT-sized blocks (400 x 128 each way: a warm-up each, then the
    fastest of 5 alternated tries, which a busy core cannot all slow); False where torch has no 8-bit product."""
    global _BYTES_FASTER
    if _BYTES_FASTER is None:
        x = np.random.default_rng(0).integers(0, 256, (400, 128), dtype=np.uint8)
        as_bytes, as_float = _ByteDistances(x), torch.from_numpy(x.astype(np.float32))
        try:
            as_bytes.exact_to(as_bytes)
        except (AttributeError, RuntimeError):  # no 8-bit product in this torch build
            _BYTES_FASTER = False
            return False
        products = (lambda: as_bytes.exact_to(as_bytes), lambda: torch.addmm(as_float[:, 0], as_float, as_float.T))
        products[1]()
        byte_s, float_s = np.min([[_seconds(product) for product in products] for _ in range(5)], axis=0)
        _BYTES_FASTER = bool(byte_s < float_s)
        log.debug("descriptor matching: %s products (%.3f ms against %.3f)", "8-bit" if _BYTES_FASTER else "float32",
                  1e3 * byte_s, 1e3 * float_s)
    return _BYTES_FASTER


def _seconds(fn: Callable[[], Any]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def match_ratio_many(xq: np.ndarray, xbs: Sequence[np.ndarray], ratio: float = 0.8, mutual: bool = False,
                     metric: str = "l2", forms: ByteForms | None = None) -> list[np.ndarray]:
    """Matches one query against several candidates (the per-frame fast path).

    Same result as ``[match_ratio(xq, xb, ...) for xb in xbs]``: one fused GEMM per candidate (torch) instead of
    several full-size numpy temporaries; for byte descriptors (SIFT's), exact 8-bit products where this machine runs
    them faster (``_bytes_faster``; measured in BENCHMARKS.md), their 8-bit forms taken from ``forms`` where given
    (``ByteForms``: made once for a set matched again), else made here.

    Returns:
        One ``(M_i, 2)`` int64 array per candidate.
    """
    if len(xq) == 0 or sum(len(xb) for xb in xbs) == 0:
        return [EMPTY_MATCHES for _ in xbs]
    if metric == "hamming":
        return [match_ratio(xq, xb, ratio, mutual, metric) for xb in xbs]
    if _bytes_faster():
        form = forms if forms is not None else _form
        query, cands = form(xq), [None if len(xb) == 0 else form(xb) for xb in xbs]
        if query is not None and all(c is not None or len(xb) == 0 for c, xb in zip(cands, xbs)):
            return [EMPTY_MATCHES if c is None else _ratio_from_distances(query.exact_to(c), ratio, mutual, True)
                    for c in cands]
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
