"""Cosine top-k over stored codes (faiss), and the keyframe index that excludes recent frames.

Codes are L2-normalised, so the inner product is the cosine similarity. faiss-contrib conventions: numpy in and
out, ``xq`` queries ``(nq, d)``, ``xb`` database ``(nb, d)``, ``k``; ``D`` scores ``(nq, k)`` and ``I`` positions
``(nq, k)``, ``-1`` where fewer than ``k`` codes exist.

Index types, by registry name (``index.name``):

- ``flat``: exact, float32 (4 bytes per dimension).
- ``fp16``: exact up to float16 rounding (2 bytes per dimension).
- ``hnsw``: approximate graph search over float32 codes (HNSW, Malkov & Yashunin), for very large maps.
- ``sq8``: 8-bit scalar quantisation, one byte per dimension (per-dimension range learned from the first codes).
"""

from __future__ import annotations

from collections import deque
from typing import Any

import faiss
import numpy as np

from core.conf import Float, Int, Registry, configure, merge_conf

__all__ = ["AdmissionQueue", "CodeIndex", "FlatIndex", "FP16Index", "SQ8Index", "HNSWIndex", "INDEXES", "create_index", "KeyframeIndex",
           "brute_force_search"]


def brute_force_search(xq: np.ndarray, xb: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Reference top-k by inner product in plain numpy (ties broken by lower position). Returns ``D, I``."""
    xq = np.asarray(xq, np.float32).reshape(len(xq), -1)
    nq = len(xq)
    D = np.full((nq, k), -np.inf, np.float32)
    I = np.full((nq, k), -1, np.int64)
    if len(xb) == 0 or nq == 0:
        return D, I
    sims = xq @ np.asarray(xb, np.float32).T
    order = np.argsort(-sims, axis=1, kind="stable")[:, :k]
    D[:, : order.shape[1]] = np.take_along_axis(sims, order, 1)
    I[:, : order.shape[1]] = order
    return D, I


class CodeIndex:
    """Base: a faiss inner-product index built from ``factory`` (subclasses set it and their conf)."""

    default_conf: dict[str, Any] = {"name": "flat"}
    conf_rules: dict[str, Any] = {}
    factory = "Flat"

    def __init__(self, dim: int, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "index")
        self.dim = dim
        self.index = faiss.index_factory(dim, self.factory, faiss.METRIC_INNER_PRODUCT)
        self._configure()

    def _configure(self) -> None:
        """Hook for subclasses to set search parameters."""

    @property
    def ntotal(self) -> int:
        return int(self.index.ntotal)

    def add(self, xb: np.ndarray) -> None:
        """Appends ``(n, d)`` codes; their positions continue from ``ntotal``."""
        xb = np.ascontiguousarray(xb, np.float32).reshape(-1, self.dim)
        if len(xb):
            self.index.add(xb)

    def search(self, xq: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-``k`` by inner product: ``D (nq, k)`` float32, ``I (nq, k)`` int64 (``-1`` padding)."""
        xq = np.ascontiguousarray(xq, np.float32).reshape(-1, self.dim)
        if len(xq) == 0 or k <= 0:
            return np.zeros((len(xq), max(k, 0)), np.float32), np.full((len(xq), max(k, 0)), -1, np.int64)
        D, I = self.index.search(xq, k)
        D[I < 0] = -np.inf
        return D, I.astype(np.int64)

    def bytes_per_code(self) -> float:
        """Memory of the stored codes per vector (serialised index size / ntotal, at least one code)."""
        return faiss.serialize_index(self.index).nbytes / max(1, self.ntotal)


INDEXES: Registry[CodeIndex] = Registry("index")


@INDEXES.register("flat")
class FlatIndex(CodeIndex):
    default_conf: dict[str, Any] = {"name": "flat"}  # exact search over float32 codes
    factory = "Flat"


@INDEXES.register("fp16")
class FP16Index(CodeIndex):
    default_conf: dict[str, Any] = {"name": "fp16"}  # exact search over float16-rounded codes, half the memory
    factory = "SQfp16"


@INDEXES.register("hnsw")
class HNSWIndex(CodeIndex):
    default_conf: dict[str, Any] = {
        "name": "hnsw",
        "m": 32,  # graph degree (faiss HNSW M): more = better recall, more memory
        "ef_search": 128,  # candidate list size at search time: more = better recall, slower
        "ef_construction": 64,  # candidate list size while inserting
    }
    conf_rules: dict[str, Any] = {"m": Int(2, 512), "ef_search": Int(1, 100_000), "ef_construction": Int(1, 100_000)}

    def __init__(self, dim: int, conf: dict[str, Any] | None = None) -> None:
        self.factory = f"HNSW{merge_conf(self.default_conf, conf, 'index')['m']}"
        super().__init__(dim, conf)

    def _configure(self) -> None:
        self.index.hnsw.efSearch = self.conf["ef_search"]
        self.index.hnsw.efConstruction = self.conf["ef_construction"]


def create_index(dim: int, conf: dict[str, Any] | None = None) -> CodeIndex:
    """The index named by ``conf["name"]`` (default ``"flat"``)."""
    return INDEXES.get((conf or {}).get("name", "flat"))(dim, conf)


class AdmissionQueue:
    """Keyframes wait here until they are old enough to be matched by the current query: at least
    ``exclude_recent`` frames earlier and, when timestamps are given, ``exclude_recent_s`` seconds earlier (the one
    rule for "too recent", shared by every place memory). Frames come in increasing id (and timestamp) order."""

    def __init__(self, exclude_recent: int = 0, exclude_recent_s: float | None = None) -> None:
        self.exclude_recent = int(exclude_recent)
        self.exclude_recent_s = exclude_recent_s
        self._pending: deque[tuple[int, float | None, Any]] = deque()

    def __len__(self) -> int:
        return len(self._pending)

    def push(self, frame_id: int, timestamp: float | None, item: Any) -> None:
        self._pending.append((int(frame_id), timestamp, item))

    def pop_ready(self, frame_id: int, timestamp: float | None = None) -> list[tuple[int, Any]]:
        """``(frame id, item)`` of every queued keyframe old enough for a query at ``frame_id`` (and ``timestamp``),
        oldest first; they leave the queue."""
        ready = []
        while self._pending:
            fid, ts, item = self._pending[0]
            if frame_id - fid < self.exclude_recent:
                break
            if self.exclude_recent_s is not None and timestamp is not None and ts is not None \
                    and timestamp - ts < self.exclude_recent_s:
                break
            self._pending.popleft()
            ready.append((fid, item))
        return ready


class KeyframeIndex:
    """Keyframe codes searchable by cosine, with recent frames excluded.

    A code becomes searchable only once it is old enough relative to the query (``AdmissionQueue``). Codes wait in
    the queue until ``admit`` moves them into the index, so the exclusion costs nothing at search time and works
    with every index type (none needs deletion); ``search`` only reads.

        >>> index.admit(frame_id, timestamp)        # codes old enough for this frame become searchable
        >>> scores, ids = index.search(code, k)     # doctest: +SKIP
    """

    def __init__(self, dim: int, index_conf: dict[str, Any] | None = None, exclude_recent: int = 0,
                 exclude_recent_s: float | None = None) -> None:
        self.index = create_index(dim, index_conf)
        self.frame_ids: list[int] = []  # position in the index -> frame id
        self._queue = AdmissionQueue(exclude_recent, exclude_recent_s)

    def __len__(self) -> int:
        return len(self.frame_ids) + len(self._queue)

    def add(self, frame_id: int, code: np.ndarray, timestamp: float | None = None) -> None:
        """Queues a keyframe's unit-norm ``(d,)`` code."""
        self._queue.push(frame_id, timestamp, np.asarray(code, np.float32).reshape(-1))

    def admit(self, frame_id: int, timestamp: float | None = None) -> None:
        """Makes searchable every queued code old enough for a query at ``frame_id`` (and ``timestamp``)."""
        ready = self._queue.pop_ready(frame_id, timestamp)
        if ready:
            self.frame_ids.extend(fid for fid, _ in ready)
            self.index.add(np.stack([code for _, code in ready]))

    def search(self, code: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-``k`` among the admitted keyframes (call ``admit`` for the query frame first); changes nothing.

        Returns:
            ``scores (m,)`` float32 cosine similarities, best first, and ``frame_ids (m,)`` int64, ``m <= k``.
        """
        D, I = self.index.search(np.asarray(code, np.float32).reshape(1, -1), k)
        keep = I[0] >= 0
        ids = np.asarray(self.frame_ids, np.int64)
        return D[0][keep], ids[I[0][keep]] if len(ids) else np.zeros(0, np.int64)


@INDEXES.register("sq8")
class SQ8Index(CodeIndex):
    """8-bit scalar quantisation (faiss ``SQ8``): 1 byte per dimension, a quarter of ``flat``, approximate scores.

    The quantiser needs each dimension's range: the first ``train_size`` codes are kept exact (float32, searched
    by brute force); when that many are stored the ranges are learned from them (widened by ``margin``) and every
    code is quantised from then on. Values outside a learned range are clipped, so train on representative codes.
    """

    default_conf: dict[str, Any] = {
        "name": "sq8",
        "train_size": 1000,  # codes kept exact until this many are stored; the quantiser is then learned from them
        "margin": 0.1,  # widen each learned range by this fraction of it on both sides (room for unseen values)
    }
    conf_rules: dict[str, Any] = {"train_size": Int(1), "margin": Float(0, 10)}
    factory = "SQ8"

    def _configure(self) -> None:
        self.index.sq.rangestat_arg = float(self.conf["margin"])
        self._pending: list[np.ndarray] = []

    @property
    def ntotal(self) -> int:
        return int(self.index.ntotal) + sum(len(x) for x in self._pending)

    def add(self, xb: np.ndarray) -> None:
        xb = np.ascontiguousarray(xb, np.float32).reshape(-1, self.dim)
        if self.index.is_trained:
            if len(xb):
                self.index.add(xb)
            return
        self._pending.append(xb.copy())
        if self.ntotal >= max(1, int(self.conf["train_size"])):
            codes = np.concatenate(self._pending)
            self.index.train(codes)
            self.index.add(codes)
            self._pending = []

    def search(self, xq: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        if self.index.is_trained:
            return super().search(xq, k)
        xq = np.ascontiguousarray(xq, np.float32).reshape(-1, self.dim)
        stored = np.concatenate(self._pending) if self._pending else np.zeros((0, self.dim), np.float32)
        return brute_force_search(xq, stored, max(k, 0))

    def bytes_per_code(self) -> float:
        return super().bytes_per_code() if self.index.is_trained else 4.0 * self.dim
from . import milvus_index  # noqa: F401,E402  (registers the Milvus code index: milvus; pymilvus loads on first use)
