"""Cosine top-k over stored codes (faiss), and the keyframe index that excludes recent frames.

Codes are L2-normalised, so the inner product is the cosine similarity. faiss-contrib conventions: numpy in and
out, ``xq`` queries ``(nq, d)``, ``xb`` database ``(nb, d)``, ``k``; ``D`` scores ``(nq, k)`` and ``I`` positions
``(nq, k)``, ``-1`` where fewer than ``k`` codes exist.

Index types, by registry name (``index.name``):

- ``flat``: exact, float32 (4 bytes per dimension).
- ``fp16``: exact up to float16 rounding (2 bytes per dimension).
- ``hnsw``: approximate graph search (HNSW, Malkov & Yashunin) over float16 codes (``storage``; or float32), for
  very large maps.
- ``sq8``: 8-bit scalar quantisation, one byte per dimension (per-dimension range learned from the first codes).
- ``ivfpq``: OPQ rotation, inverted file and product quantisation, re-ranked on float16 codes (learned from the
  first codes; exact brute force until then): a million codes in well under 2 GiB, ~1 ms a query.
- ``auto``: picks by search cost: exact (``small``: ``fp16`` by default) while small, then rebuilds itself once as
  the ``large`` index (``hnsw`` by default) when exact search would scan ``switch_cost`` numbers a query (codes x
  dimension: ~30 k whitened 256-d codes, ~2 k raw 4096-d ones), or at ``switch_at`` codes.

Every index saves to and loads from a file (``CodeIndex.save`` / ``load_index``). ``KeyframeIndex.save`` writes its
frame ids beside the faiss index, and a detector with a keyframe store saves it there on ``close`` (``keyframes.h5``
-> ``keyframes.h5.index``) and restores it on resume instead of rebuilding it, for the indexes whose rebuild costs
(``save_with_store``: graph and trained ones; exact ones are rebuilt from the store's codes as fast).
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections import deque
from pathlib import Path
from typing import Any, Iterator, Mapping

import faiss
import numpy as np

from cae_lcd.core.conf import Choice, Float, Int, Registry, configure
from cae_lcd.core.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["AdmissionQueue", "CodeIndex", "FlatIndex", "FP16Index", "SQ8Index", "HNSWIndex", "IVFPQIndex", "AutoIndex",
           "INDEXES", "create_index", "load_index", "read_index_file", "write_index_file", "KeyframeIndex",
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
    #: a keyframe store saves this index beside it (graph and trained indexes: rebuilding one from the stored codes
    #: costs minutes at a million); an exact one (flat, fp16) is rebuilt from the store's codes as fast as a saved
    #: copy would load
    save_with_store = True
    #: ``reconstruct`` gives back exactly the codes added (flat; fp16 and HNSW for float16-rounded codes):
    #: a place memory then reads its stored codes from the index instead of keeping a second copy
    exact_codes = True

    def __init__(self, dim: int, conf: dict[str, Any] | None = None) -> None:
        self.conf = configure(self, conf, "index")
        self.dim = dim
        self.index = faiss.index_factory(dim, self._factory(), faiss.METRIC_INNER_PRODUCT)
        self._configure()

    def _factory(self) -> str:
        """The faiss factory string of ``self.index`` (``factory``; subclasses may choose it by their conf)."""
        return self.factory

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

    def reconstruct(self, positions: np.ndarray) -> np.ndarray:
        """The stored codes at ``positions`` ``(n,)``: ``(n, d)`` float32 (exact where ``exact_codes``)."""
        positions = np.asarray(positions, np.int64).reshape(-1)
        if not len(positions):
            return np.zeros((0, self.dim), np.float32)
        return np.asarray(self.index.reconstruct_batch(positions), np.float32).reshape(len(positions), self.dim)

    def bytes_per_code(self) -> float:
        """Memory of the stored codes per vector (serialised index size / ntotal, at least one code)."""
        return faiss.serialize_index(self.index).nbytes / max(1, self.ntotal)

    def _parts(self) -> dict[str, Any]:
        """The faiss indexes this object holds, by attribute name (``save`` writes them all)."""
        return {"index": self.index}

    def _set_part(self, name: str, part: Any) -> None:
        """Takes back a part ``_parts`` named (``load_index``)."""
        setattr(self, name, part)

    def save(self, path: str | Path) -> None:
        """Writes the index to ``path`` atomically (``write_index_file`` without arrays)."""
        write_index_file(path, self)


def write_index_file(path: str | Path, index: CodeIndex, arrays: Mapping[str, np.ndarray] | None = None) -> None:
    """Writes ``index`` and named 1-d ``arrays`` to ``path`` atomically (a temporary file, then a rename; the
    temporary file is removed when writing fails): a JSON header (conf, dimension, part and array sizes), each faiss
    part serialised, then each array's bytes."""
    path = Path(path)
    blobs = {name: faiss.serialize_index(part).tobytes() for name, part in index._parts().items()}
    arrs = {name: np.ascontiguousarray(a).reshape(-1) for name, a in (arrays or {}).items()}
    head = json.dumps({"conf": index.conf, "dim": index.dim, "parts": [[n, len(b)] for n, b in blobs.items()],
                       "arrays": [[n, a.dtype.str, len(a)] for n, a in arrs.items()]}).encode()
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(len(head).to_bytes(8, "little") + head)
            for blob in blobs.values():
                fh.write(blob)
            for a in arrs.values():
                fh.write(a.tobytes())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def read_index_file(path: str | Path) -> tuple[CodeIndex, dict[str, np.ndarray]]:
    """The index and arrays ``write_index_file`` wrote, as they were (same conf, codes and search parameters).

    Raises:
        ConfigError: not an index file, or damaged.
    """
    try:
        data = Path(path).read_bytes()
        pos = 8 + int.from_bytes(data[:8], "little")
        head = json.loads(data[8:pos])
        index = create_index(int(head["dim"]), head["conf"])
        for name, size in head["parts"]:
            if pos + size > len(data):
                raise ValueError("truncated")
            index._set_part(name, faiss.deserialize_index(np.frombuffer(data, np.uint8, size, pos)))
            pos += size
        index._configure()
        arrays = {}
        for name, dtype, count in head.get("arrays", []):
            arrays[name] = np.frombuffer(data, np.dtype(dtype), int(count), pos).copy()
            pos += arrays[name].nbytes
    except (OSError, ValueError, KeyError, TypeError, RuntimeError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path} is not a readable code index ({type(err).__name__}: {str(err)[:120]})") from None
    return index, arrays


def load_index(path: str | Path) -> "CodeIndex":
    """An index written by ``CodeIndex.save``, as it was (``read_index_file`` without the arrays).

    Raises:
        ConfigError: not an index file, or damaged.
    """
    return read_index_file(path)[0]


INDEXES: Registry[CodeIndex] = Registry("index")


@INDEXES.register("flat")
class FlatIndex(CodeIndex):
    default_conf: dict[str, Any] = {"name": "flat"}  # exact search over float32 codes
    factory = "Flat"
    save_with_store = False


@INDEXES.register("fp16")
class FP16Index(CodeIndex):
    default_conf: dict[str, Any] = {"name": "fp16"}  # exact search over float16-rounded codes, half the memory
    factory = "SQfp16"
    save_with_store = False


@INDEXES.register("hnsw")
class HNSWIndex(CodeIndex):
    default_conf: dict[str, Any] = {
        "name": "hnsw",
        "m": 32,  # graph degree (faiss HNSW M): more = better recall, more memory
        "ef_search": 256,  # candidate list size at search time: more = better recall, slower (chosen on 1M
        #                    realistic codes with ef_construction: BENCHMARKS.md, issue 18, "a million keyframes")
        "ef_construction": 128,  # candidate list size while inserting: the graph's quality bounds the recall
        "storage": "fp16",  # how the graph keeps the codes: "fp16" (half of float32's memory, exact for the
        #                     detector's float16-rounded entries, and scanned as fast) or "flat" (float32)
    }
    conf_rules: dict[str, Any] = {"m": Int(2, 512), "ef_search": Int(1, 100_000), "ef_construction": Int(1, 100_000),
                                  "storage": Choice("flat", "fp16")}

    def _factory(self) -> str:
        return f"HNSW{self.conf['m']}" + ("_SQfp16" if self.conf["storage"] == "fp16" else "")

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

    def __iter__(self) -> Iterator[tuple[int, float | None, Any]]:
        """``(frame id, timestamp, item)`` of the queued keyframes, oldest first."""
        return iter(self._pending)

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
        self._ids = np.zeros(64, np.int64)  # position in the index -> frame id, the first ``_n`` (grown by doubling)
        self._n = 0
        self._queue = AdmissionQueue(exclude_recent, exclude_recent_s)

    @property
    def frame_ids(self) -> np.ndarray:
        """``(n,)`` int64: the admitted keyframes' frame ids by position in the index (admitted in increasing frame
        order; a view, valid until the next ``admit``)."""
        view = self._ids[: self._n]
        view.flags.writeable = False
        return view

    def _set_ids(self, ids: np.ndarray) -> None:
        self._ids, self._n = np.array(ids, np.int64).reshape(-1), len(ids)

    def __len__(self) -> int:
        return self._n + len(self._queue)

    def add(self, frame_id: int, code: np.ndarray, timestamp: float | None = None) -> None:
        """Queues a keyframe's unit-norm ``(d,)`` code."""
        self._queue.push(frame_id, timestamp, np.asarray(code, np.float32).reshape(-1))

    def admit(self, frame_id: int, timestamp: float | None = None) -> None:
        """Makes searchable every queued code old enough for a query at ``frame_id`` (and ``timestamp``)."""
        ready = self._queue.pop_ready(frame_id, timestamp)
        if ready:
            if self._n + len(ready) > len(self._ids):
                self._ids = np.resize(self._ids, max(2 * len(self._ids), self._n + len(ready), 64))
            self._ids[self._n:self._n + len(ready)] = [fid for fid, _ in ready]
            self._n += len(ready)
            self.index.add(np.stack([code for _, code in ready]))

    def save(self, path: str | Path) -> bool:
        """Writes the admitted codes' index and their frame ids to ``path`` (``write_index_file``) when the index is
        worth keeping beside a keyframe store (``CodeIndex.save_with_store``); returns whether it wrote."""
        if not self.index.save_with_store:
            return False
        write_index_file(path, self.index, {"frame_ids": np.asarray(self.frame_ids, np.int64)})
        return True

    def restore(self, path: str | Path, keyframe_ids: np.ndarray) -> int:
        """Takes back, into this empty index, what ``save`` wrote, when its frame ids are the first of a keyframe
        store's ``keyframe_ids`` ``(n,)`` (a store only appends: the keyframes after them are added as usual) and it
        was made with this index's conf.

        Returns:
            How many of ``keyframe_ids`` the restored index holds; 0 when nothing was restored (no file, or one that
            does not fit: logged), and the caller adds every keyframe again.
        """
        if len(self) or not Path(path).is_file():
            return 0
        try:
            index, arrays = read_index_file(path)
        except ConfigError as err:
            log.warning("%s; the index is rebuilt from the keyframe store", err)
            return 0
        ids = arrays.get("frame_ids", np.zeros(0, np.int64))
        keyframe_ids = np.asarray(keyframe_ids, np.int64)
        if index.conf != self.index.conf or index.dim != self.index.dim or index.ntotal != len(ids) \
                or len(ids) > len(keyframe_ids) or not np.array_equal(ids, keyframe_ids[:len(ids)]):
            log.warning("%s was saved for other keyframes or another index; the index is rebuilt from the keyframe "
                        "store", path)
            return 0
        self.index = index
        self._set_ids(ids)
        return len(ids)

    def mapped(self, fn: Any, dim: int, codes_of: Any) -> "KeyframeIndex":
        """A copy in another code space: the same admitted and queued keyframes, each code ``fn(code)`` (``(n, D)``
        -> ``(n, dim)``); ``codes_of(frame_ids) -> (n, D)`` gives their codes, the admitted and the queued ones' (a
        stream's whitening, fitted on its keyframes: ``retrieval.places``)."""
        out = KeyframeIndex(dim, self.index.conf, self._queue.exclude_recent, self._queue.exclude_recent_s)
        out._set_ids(self.frame_ids)
        if out._n:
            out.index.add(fn(codes_of(out.frame_ids)))
        for fid, ts, _ in self._queue:
            out._queue.push(fid, ts, fn(codes_of(np.array([fid], np.int64)))[0])
        return out

    def search(self, code: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Top-``k`` among the admitted keyframes (call ``admit`` for the query frame first); changes nothing.

        Returns:
            ``scores (m,)`` float32 cosine similarities, best first, and ``frame_ids (m,)`` int64, ``m <= k``.
        """
        D, I = self.index.search(np.asarray(code, np.float32).reshape(1, -1), k)
        keep = I[0] >= 0
        return D[0][keep], self.frame_ids[I[0][keep]]

    def queued_ids(self) -> list[int]:
        """Frame ids of the keyframes still queued (not searchable yet), oldest first."""
        return [fid for fid, _, _ in self._queue]

    def _position(self, frame_id: int) -> int:
        """The admitted keyframe's position in the index, -1 if not admitted (admitted in increasing frame order)."""
        ids = self.frame_ids
        pos = int(np.searchsorted(ids, frame_id))
        return pos if pos < len(ids) and ids[pos] == frame_id else -1

    def holds(self, frame_id: int) -> bool:
        """True when the keyframe is queued or admitted."""
        fid = int(frame_id)
        return self._position(fid) >= 0 or any(q == fid for q, _, _ in self._queue)

    def codes(self, frame_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The codes of keyframes this index holds (queued or admitted; exact where ``CodeIndex.exact_codes``).

        Returns:
            ``found (n,)`` bool and ``codes (n, d)`` float32 (zeros where not found).
        """
        fids = np.asarray(frame_ids, np.int64).reshape(-1)
        found, out = np.zeros(len(fids), bool), np.zeros((len(fids), self.index.dim), np.float32)
        ids = self.frame_ids
        pos = np.minimum(np.searchsorted(ids, fids), max(len(ids) - 1, 0))
        admitted = ids[pos] == fids if len(ids) else np.zeros(len(fids), bool)
        rest = np.flatnonzero(~admitted)  # queued ones among them (a code is queued or admitted, never both)
        if len(self._queue) and len(rest):
            queued = {fid: code for fid, _, code in self._queue}
            for row in rest.tolist():
                code = queued.get(int(fids[row]))
                if code is not None:
                    out[row], found[row] = code, True
        if admitted.any():
            out[admitted], found[admitted] = self.index.reconstruct(pos[admitted]), True
        return found, out


class TrainedIndex(CodeIndex):
    """Base of the indexes that learn from the codes (quantisers): the first ``train_size`` codes are kept exact
    (float32, searched by brute force); when that many are stored the index is trained on them and every code is
    added to it from then on."""

    default_conf: dict[str, Any] = {"name": "trained", "train_size": 1000}
    exact_codes = False  # quantised once trained

    def __init__(self, dim: int, conf: dict[str, Any] | None = None) -> None:
        self.exact = faiss.IndexFlatIP(dim)  # the codes stored before training
        self.train_seconds = 0.0  # what learning the quantisers took (once, at train_size codes)
        super().__init__(dim, conf)

    def _parts(self) -> dict[str, Any]:
        return {"index": self.index, "exact": self.exact}

    @property
    def ntotal(self) -> int:
        return int(self.index.ntotal) + int(self.exact.ntotal)

    def add(self, xb: np.ndarray) -> None:
        xb = np.ascontiguousarray(xb, np.float32).reshape(-1, self.dim)
        if self.index.is_trained:
            if len(xb):
                self.index.add(xb)
            return
        if len(xb):
            self.exact.add(xb)
        if self.exact.ntotal >= max(1, int(self.conf["train_size"])):
            codes = self.exact.reconstruct_n(0, self.exact.ntotal)
            t0 = time.perf_counter()
            self.index.train(codes)
            self.train_seconds = time.perf_counter() - t0
            log.info("index %s learned from %d codes in %.1f s", self.conf["name"], len(codes), self.train_seconds)
            self.index.add(codes)
            self.exact.reset()

    def search(self, xq: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        if self.index.is_trained:
            return super().search(xq, k)
        xq = np.ascontiguousarray(xq, np.float32).reshape(-1, self.dim)
        if len(xq) == 0 or k <= 0 or self.exact.ntotal == 0:
            return brute_force_search(xq, np.zeros((0, self.dim), np.float32), max(k, 0))
        D, I = self.exact.search(xq, k)
        D[I < 0] = -np.inf
        return D, I.astype(np.int64)

    def bytes_per_code(self) -> float:
        return super().bytes_per_code() if self.index.is_trained else 4.0 * self.dim


@INDEXES.register("sq8")
class SQ8Index(TrainedIndex):
    """8-bit scalar quantisation (faiss ``SQ8``): 1 byte per dimension, a quarter of ``flat``, approximate scores.

    The quantiser needs each dimension's range, learned from the first ``train_size`` codes (widened by
    ``margin``). Values outside a learned range are clipped, so train on representative codes.
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


@INDEXES.register("ivfpq")
class IVFPQIndex(TrainedIndex):
    """OPQ + IVF + PQ (Jegou et al.; Ge et al.), each query's shortlist re-ranked on float16 codes (faiss
    ``OPQm,IVFn,PQm,Refine(SQfp16)``): ~``2 * dim + m`` bytes a code, sub-linear search. Learned from the first
    ``train_size`` codes (exact brute force until then)."""

    default_conf: dict[str, Any] = {
        "name": "ivfpq",
        "nlist": 1024,  # inverted lists (k-means cells); about sqrt(codes expected) to 4 * sqrt
        "m": 32,  # PQ sub-quantisers of 8 bits (bytes a code in the lists); must divide the code dimension
        "opq": True,  # learn a rotation (OPQ) before PQ: better recall for the same bytes
        "nprobe": 32,  # lists visited per query: more = better recall, slower
        "k_factor": 8,  # the top k * k_factor of the PQ search are re-ranked on float16 codes
        "train_size": 20_000,  # codes kept exact until this many are stored; the quantisers are then learned
    }
    conf_rules: dict[str, Any] = {"nlist": Int(1, 1 << 20), "m": Int(1, 512), "opq": Choice(True, False),
                                  "nprobe": Int(1, 1 << 20), "k_factor": Int(1, 1000), "train_size": Int(1)}

    def _factory(self) -> str:
        c = self.conf
        if self.dim % int(c["m"]):
            raise ConfigError(f"index.m ({c['m']}) must divide the code dimension ({self.dim})")
        opq = f"OPQ{c['m']}," if c["opq"] else ""
        return f"{opq}IVF{c['nlist']},PQ{c['m']},Refine(SQfp16)"

    def _configure(self) -> None:
        faiss.extract_index_ivf(self.index).nprobe = int(self.conf["nprobe"])
        faiss.downcast_index(self.index).k_factor = float(self.conf["k_factor"])


@INDEXES.register("auto")
class AutoIndex(CodeIndex):
    """Picks by search cost: exact search (the ``small`` index) while a query scans fewer than ``switch_cost``
    numbers (codes x dimension) and the map holds fewer than ``switch_at`` codes; then rebuilds itself as the
    ``large`` index (its registry defaults) from the codes it holds, and stays that (the switch depends on the codes
    added only, so a resumed run switches where the uninterrupted one did)."""

    default_conf: dict[str, Any] = {
        "name": "auto",
        "small": "fp16",  # the exact index until the switch: fp16 holds the detector's entries exactly (they are
        #                   float16-rounded: places.CodePlaces.entry) in half of flat's memory, and scans faster;
        #                   "flat" for codes that are not rounded
        "switch_at": 100_000,  # codes at which exact search gives way to the large index whatever their dimension
        "switch_cost": 1 << 23,  # codes x dimension at which it gives way (exact search then costs ~3 ms a query,
        #                          linear in the map, against well under 1 ms for HNSW); None: by switch_at only
        "large": "hnsw",  # the index used from the switch on (registry name, with its defaults)
    }
    conf_rules: dict[str, Any] = {"switch_at": Int(1), "switch_cost": Int(1, optional=True),
                                  "small": Choice("flat", "fp16"),
                                  "large": Choice("flat", "fp16", "sq8", "hnsw", "ivfpq")}

    def _factory(self) -> str:
        return INDEXES.get(self.conf["small"]).factory

    def _configure(self) -> None:
        self.large: CodeIndex | None = getattr(self, "large", None)

    def _parts(self) -> dict[str, Any]:
        large = {} if self.large is None else {f"large.{n}": p for n, p in self.large._parts().items()}
        return {"index": self.index, **large}

    def _set_part(self, name: str, part: Any) -> None:
        if not name.startswith("large."):
            return super()._set_part(name, part)
        if self.large is None:
            self.large = create_index(self.dim, {"name": self.conf["large"]})
        self.large._set_part(name[len("large."):], part)
        self.large._configure()

    @property
    def save_with_store(self) -> bool:  # type: ignore[override]
        return self.large is not None and self.large.save_with_store

    @property
    def exact_codes(self) -> bool:  # type: ignore[override]
        """Both stages give back the codes exactly (decided before the switch: a memory relies on it all along)."""
        return INDEXES.get(self.conf["small"]).exact_codes and INDEXES.get(self.conf["large"]).exact_codes

    def reconstruct(self, positions: np.ndarray) -> np.ndarray:
        return super().reconstruct(positions) if self.large is None else self.large.reconstruct(positions)

    @property
    def chosen(self) -> str:
        """The index in use now: the ``small`` one's name or the ``large`` one's."""
        return self.conf["small"] if self.large is None else self.conf["large"]

    @property
    def ntotal(self) -> int:
        return self.index.ntotal if self.large is None else self.large.ntotal

    def add(self, xb: np.ndarray) -> None:
        if self.large is not None:
            self.large.add(xb)
            return
        super().add(xb)
        cost = self.conf.get("switch_cost")
        if self.index.ntotal >= self.conf["switch_at"] or (cost is not None and self.index.ntotal * self.dim >= cost):
            large = create_index(self.dim, {"name": self.conf["large"]})
            large.add(self.index.reconstruct_n(0, self.index.ntotal))
            self.large, self.index = large, faiss.index_factory(self.dim, self._factory(), faiss.METRIC_INNER_PRODUCT)

    def search(self, xq: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        return super().search(xq, k) if self.large is None else self.large.search(xq, k)

    def bytes_per_code(self) -> float:
        return super().bytes_per_code() if self.large is None else self.large.bytes_per_code()


from . import milvus_index  # noqa: F401,E402  (registers the Milvus code index: milvus; pymilvus loads on first use)
