"""The place memory: where the detector keeps what it has seen and finds the candidates of a query.

What a descriptor gives decides how it is stored and compared (``GlobalDescriptor.searched_by``):

- ``cosine`` (``CodePlaces``): a unit-norm code per frame (CAE, thumbnail, bovw), whitened when a whitening is
  given, searched by cosine top-k in a faiss index; the temporal filter reads similarities from a ``CodeTable``.
  Without a whitening, a stream may fit its own (``stream_fit``): raw codes are searched for its first
  ``stream_fit`` keyframes, then a whitening is fitted on them (``Whitening.fit``, as the calibration fits one) and
  the memory re-indexed in the whitened space once: a long stream's index and table hold short codes.
- ``hash`` (``HashPlaces``): a frame's binary descriptors (MILD), in multi-index hash tables; a query scores every
  admitted keyframe (MILD eq. 3), so the whole similarity row is returned (MILD's Bayesian filter needs it); the
  filter reads similarities from the rows of the recent queries (``RowTable``).

Both exclude keyframes too recent for the query with the same rule (``retrieval.index.AdmissionQueue``). The
interface, shapes included::

    entry = places.entry(code)                # what is searched: the normalised code / the descriptors
    places.stored(entry)                      # what the keyframe store keeps of it (rows); ``check`` takes it back
    places.check(entry)                       # a stored entry this memory cannot use -> ConfigError
    scores, ids = places.search(frame_id, entry, timestamp, k)   # (m,) float32 best first, (m,) int64
    places.register(frame_id, entry, timestamp)  # what search changes, without searching (resuming)
    places.insert(frame_id, entry, timestamp) # the frame becomes a keyframe (searchable once old enough)
    places.undo(frame_id)                     # the frame was not inserted after all (search registered it)
    places.save_index(path)                   # beside a keyframe store, on close: True when written
    places.restore_index(path, keyframe_ids)  # on resume, before registering: how many keyframes it already holds
    places.source                             # temporal.SimilaritySource over the stored frames
    len(places)                               # keyframes inserted (searchable or still too recent)

``code_entry(code, whitening)`` makes a code's searched entry (``CodePlaces.entry`` and ``rewhiten`` use it; the
fleet's place memory makes its own entries with it, in its one fixed whitening).
"""

from __future__ import annotations

import functools
import logging
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np

from cae.whitening import SAMPLES_PER_DIM, Whitening
from cae_lcd.core.conf import ConfigError, Registry

from .descriptors import GlobalDescriptor
from .index import AdmissionQueue, KeyframeIndex
from .temporal import CodeTable

__all__ = ["Places", "CodePlaces", "HashPlaces", "RowTable", "PLACES", "create_places", "code_entry"]

log = logging.getLogger(__name__)


def code_entry(code: np.ndarray, whitening: Whitening | None) -> np.ndarray:
    """The searched entry of raw codes ``(D,)`` or ``(n, D)``: whitened (when a whitening is given: unit norm),
    rounded to float16 precision (what a keyframe store keeps) -> ``(d,)`` / ``(n, d)`` float32."""
    x = code if whitening is None else whitening.transform(code)
    return np.asarray(x, np.float16).astype(np.float32)


class Places:
    """Base of the place memories (see the module doc)."""

    source: Any

    def check(self, code: np.ndarray) -> None:
        raise NotImplementedError

    def entry(self, code: np.ndarray) -> np.ndarray:
        return code

    def stored(self, entry: np.ndarray) -> np.ndarray:
        """What the keyframe store keeps of an entry (a resume gives ``check`` and ``insert`` its flat form)."""
        return entry

    def search(self, frame_id: int, entry: np.ndarray, timestamp: float | None,
               k: int) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def insert(self, frame_id: int, entry: np.ndarray, timestamp: float | None) -> None:
        raise NotImplementedError

    def register(self, frame_id: int, entry: np.ndarray, timestamp: float | None) -> None:
        """What ``search`` changes, without the result (a resume whose filter needs no replay of every search)."""
        self.search(frame_id, entry, timestamp, 1)

    def undo(self, frame_id: int) -> None:
        raise NotImplementedError

    def save_index(self, path: str | Path) -> bool:
        """Writes what a resume would otherwise rebuild to ``path``; False: nothing worth saving (the default)."""
        return False

    def restore_index(self, path: str | Path, keyframe_ids: np.ndarray) -> int:
        """Takes back what ``save_index`` wrote for the first of a store's ``keyframe_ids`` ``(n,)``; returns how
        many it holds (their ``insert`` then adds nothing again); 0: nothing restored (the default)."""
        return 0

    def __len__(self) -> int:
        raise NotImplementedError


PLACES: Registry[Places] = Registry("place memory")


@PLACES.register("cosine")
class CodePlaces(Places):
    """Codes searched by cosine top-k (faiss), whitened first when a whitening is given."""

    def __init__(self, descriptor: GlobalDescriptor, whitening: Whitening | None, conf: dict[str, Any],
                 stream_fit: int | None = None) -> None:
        self.descriptor, self.whitening = descriptor, whitening
        self.dim = dim = descriptor.dim if whitening is None else whitening.dim
        s, w = conf["search"], conf["whitening"]
        self.index = KeyframeIndex(dim, conf["index"], s["exclude_recent"], s["exclude_recent_s"])
        self.source = self._table(dim)
        self._restored_to = -1  # keyframes up to this frame id came back in a saved index (restore_index)
        self._fit_at = stream_fit if whitening is None else None  # keyframes after which a stream fits its own
        self._fit_dim = min(w["dim"], (stream_fit or 0) // SAMPLES_PER_DIM, dim)
        self._shrink = w["shrink"]
        if self._fit_at is not None and (self._fit_dim < 1 or dim % self._fit_dim or self._fit_dim == dim):
            raise ConfigError(f"whitening.stream_fit: a whitening of {self._fit_dim} dimensions fitted on "
                              f"{stream_fit} codes cannot shorten {dim}-d codes (its length must divide theirs): "
                              "change whitening.dim or whitening.stream_fit")

    def _table(self, dim: int) -> "CodeTable | IndexedCodes":
        """The similarity source: the index's own codes where it gives them back exactly (no second copy of every
        code), else a table of its own (float16: the entries are float16-rounded, kept exactly)."""
        if self.index.index.exact_codes:
            return IndexedCodes(lambda: self.index, dim, self._searchable)
        return CodeTable(dim, self._searchable, np.float16)

    def check(self, entry: np.ndarray) -> None:
        fitting = self._fit_at is not None and self.whitening is None  # raw codes until the stream's fit
        if entry.shape != (self.dim,) or not np.isfinite(entry).all():
            expected = f"({self.dim},)" + (" until the stream's whitening is fitted" if fitting else "")
            raise ConfigError(f"a stored code has shape {entry.shape} (expected {expected}, finite)")

    def entry(self, code: np.ndarray) -> np.ndarray:
        """The searched code: whitened (when a whitening is given), unit norm, rounded to float16 precision, as the
        keyframe store keeps it (a resumed run searches exactly what the uninterrupted one did)."""
        return code_entry(code, self.whitening)

    def stored(self, entry: np.ndarray) -> np.ndarray:
        """One row; before a stream's fit, the raw code as rows of the fitted length (the store's one width)."""
        return entry.reshape(-1, self._fit_dim) if self._fit_at is not None and self.whitening is None else entry

    def _searchable(self, refs: np.ndarray) -> np.ndarray:
        """True for keyframes the current query may match (admitted to the index: old enough)."""
        newest = int(self.index.frame_ids[-1]) if len(self.index.frame_ids) else -1
        return np.array([r <= newest and r in self.source for r in np.asarray(refs).tolist()], bool)

    def search(self, frame_id: int, entry: np.ndarray, timestamp: float | None,
               k: int) -> tuple[np.ndarray, np.ndarray]:
        self.index.admit(frame_id, timestamp)
        scores, ids = self.index.search(entry, k)
        self.source.add(frame_id, entry)
        return scores, ids

    def register(self, frame_id: int, entry: np.ndarray, timestamp: float | None) -> None:
        self.index.admit(frame_id, timestamp)  # no search: resuming 100k keyframes searched each (O(n^2))
        self.source.add(frame_id, entry)

    def insert(self, frame_id: int, entry: np.ndarray, timestamp: float | None) -> None:
        if frame_id > self._restored_to:  # else already in the index restore_index took back
            self.index.add(frame_id, entry, timestamp)
        self.source.inserted(frame_id)
        if self._fit_at is not None and self.whitening is None and len(self.source) >= self._fit_at:
            self._fit_stream()

    def _fit_stream(self) -> None:
        """Fits the stream's whitening on the codes of its keyframes so far (as searched: what the store keeps, so a
        resumed run fits the same one) and moves the index and the table into the whitened space."""
        ids, codes = self.source.items()
        w = Whitening.fit(codes, self._fit_dim, self._shrink)
        self.rewhiten(w, ids, codes)
        log.info("stream whitening fitted on %d keyframes: codes %d -> %d dimensions", len(ids), codes.shape[1], w.dim)

    def rewhiten(self, whitening: Whitening | None, ids: np.ndarray, raw: np.ndarray) -> None:
        """Moves the index and the table into ``whitening``'s space (None: the raw codes): ``raw`` ``(n, D)`` are
        the raw codes of keyframes ``ids`` ``(n,)`` (sorted, every keyframe held), each searched entry as ``entry``
        makes it (a stream's own whitening once fitted, or refitted: ``retrieval.online``)."""
        white = functools.partial(code_entry, whitening=whitening)  # as ``entry`` makes them
        dim = self.descriptor.dim if whitening is None else whitening.dim
        self.index = self.index.mapped(white, dim, lambda fids: raw[np.searchsorted(ids, fids)])
        table = self._table(dim)
        for fid, code in zip(ids.tolist(), white(raw)):
            if fid not in table:  # an index-backed source holds the inserted ones already
                table.add(fid, code)
        self.source, self.whitening, self.dim = table, whitening, dim

    def undo(self, frame_id: int) -> None:
        self.source.remove_last(frame_id)

    def save_index(self, path: str | Path) -> bool:
        return self.index.save(path)

    def restore_index(self, path: str | Path, keyframe_ids: np.ndarray) -> int:
        if self._fit_at is not None:  # a stream that fits its own whitening moves its index then: rebuilt as it was
            return 0
        n = self.index.restore(path, keyframe_ids)
        self._restored_to = int(keyframe_ids[n - 1]) if n else -1
        return n

    def __len__(self) -> int:
        return len(self.index)


class IndexedCodes:
    """A ``temporal.SimilaritySource`` over the codes a ``KeyframeIndex`` holds (queued or admitted: given back
    exactly, ``CodeIndex.exact_codes``), plus the frames searched and not inserted yet: what a ``CodeTable`` gives,
    without keeping every code a second time (a 4096-d float16 code is 8 kB a keyframe).

    Args:
        index: returns the memory's ``KeyframeIndex`` (it may replace it: a stream's whitening).
        dim: code length.
        searchable: which keyframes the current query may match.
    """

    def __init__(self, index: Any, dim: int, searchable: Any) -> None:
        self.dim, self._index, self._searchable = dim, index, searchable
        self._recent: OrderedDict[int, np.ndarray] = OrderedDict()  # searched, not inserted (yet): frame -> code

    def add(self, frame_id: int, code: np.ndarray) -> None:
        self._recent[int(frame_id)] = np.asarray(code, np.float32).reshape(-1)

    def inserted(self, frame_id: int) -> None:
        """The frame went into the index (queued): its code is read from there now."""
        self._recent.pop(int(frame_id), None)

    def remove_last(self, frame_id: int) -> None:
        """Undoes the last ``add`` (of ``frame_id``), e.g. when the database refused the frame."""
        if next(reversed(self._recent), None) == int(frame_id):
            del self._recent[int(frame_id)]

    def __len__(self) -> int:
        return len(self._index()) + len(self._recent)

    def __contains__(self, frame_id: int) -> bool:
        return int(frame_id) in self._recent or self._index().holds(frame_id)

    def _codes(self, frame_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``found (n,)`` and ``codes (n, dim)`` of ``frame_ids`` (the recent ones, then the index's)."""
        fids = np.asarray(frame_ids, np.int64).reshape(-1)
        uniq, back = np.unique(fids, return_inverse=True)
        found, codes = self._index().codes(uniq)
        for fid, code in self._recent.items():  # a few (searched, not inserted yet)
            i = int(np.searchsorted(uniq, fid))
            if i < len(uniq) and uniq[i] == fid:
                found[i], codes[i] = True, code
        return found[back], codes[back]

    def items(self) -> tuple[np.ndarray, np.ndarray]:
        """Frame ids ``(n,)`` int64 ascending and their codes ``(n, dim)`` float32."""
        index = self._index()
        ids = np.unique(np.r_[index.frame_ids, np.asarray([*index.queued_ids(), *self._recent], np.int64)])
        return ids, self._codes(ids)[1]

    def pairs(self, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
        q, r = np.asarray(queries, np.int64).reshape(-1), np.asarray(refs, np.int64).reshape(-1)
        out = np.full(len(q), np.nan, np.float32)
        if not len(q):
            return out
        found, codes = self._codes(np.concatenate([q, r]))
        ok = found[:len(q)] & found[len(q):]
        if ok.any():
            out[ok] = np.einsum("ij,ij->i", codes[:len(q)][ok], codes[len(q):][ok])
        return out

    def searchable(self, refs: np.ndarray) -> np.ndarray:
        return self._searchable(np.asarray(refs, np.int64))


class RowTable:
    """Similarity rows of the most recent queries against the keyframes admitted for them, as a
    ``temporal.SimilaritySource`` (NaN for pairs no kept row holds).

    Args:
        keep: rows kept (the oldest dropped first); a sequence filter longer than this sees missing terms.
    """

    def __init__(self, keep: int = 32) -> None:
        self.keep = keep
        self._rows: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    def set(self, query_id: int, ids: np.ndarray, sims: np.ndarray) -> None:
        """The row of ``query_id``: ``ids (n,)`` ascending keyframe ids, ``sims (n,)``."""
        self._rows[int(query_id)] = (np.asarray(ids, np.int64), np.asarray(sims, np.float32))
        while len(self._rows) > self.keep:
            self._rows.popitem(last=False)

    def drop(self, query_id: int) -> None:
        self._rows.pop(int(query_id), None)

    def pairs(self, queries: np.ndarray, refs: np.ndarray) -> np.ndarray:
        queries, refs = np.asarray(queries, np.int64), np.asarray(refs, np.int64)
        out = np.full(len(queries), np.nan, np.float32)
        for q in np.unique(queries).tolist():
            if q not in self._rows:
                continue
            ids, sims = self._rows[q]
            sel = np.flatnonzero(queries == q)
            pos = np.minimum(np.searchsorted(ids, refs[sel]), max(len(ids) - 1, 0))
            hit = (ids[pos] == refs[sel]) if len(ids) else np.zeros(len(sel), bool)
            out[sel[hit]] = sims[pos[hit]]
        return out

    def __contains__(self, frame_id: int) -> bool:
        """In the latest query's row (the keyframes it was compared with)."""
        return bool(self.searchable(np.array([frame_id], np.int64))[0])

    def searchable(self, refs: np.ndarray) -> np.ndarray:
        """In the latest query's row (admitted for it)."""
        refs = np.asarray(refs, np.int64)
        if not self._rows:
            return np.zeros(len(refs), bool)
        ids = next(reversed(self._rows.values()))[0]
        return np.isin(refs, ids)


@PLACES.register("hash")
class HashPlaces(Places):
    """Binary descriptors in MILD's multi-index hash tables; ``search`` returns the whole row, best first."""

    def __init__(self, descriptor: GlobalDescriptor, whitening: Whitening | None, conf: dict[str, Any]) -> None:
        if whitening is not None:
            raise ConfigError(f"the {descriptor.conf['name']!r} descriptor is compared by hashing; a whitening does "
                              "not apply (set whitening.enabled: false)")
        self.hash = descriptor.new_hash()
        self.queue = AdmissionQueue(conf["search"]["exclude_recent"], conf["search"]["exclude_recent_s"])
        self.frame_ids: list[int] = []  # hash image index -> frame id (ascending)
        self.source = RowTable()
        self.dim = descriptor.dim

    def check(self, code: np.ndarray) -> None:
        if code.ndim != 2 or code.shape[1] != self.dim or code.dtype != np.uint8:
            raise ConfigError(f"a stored entry has shape {code.shape} {code.dtype} (expected (n, {self.dim}) uint8 "
                              "binary descriptors)")

    def search(self, frame_id: int, entry: np.ndarray, timestamp: float | None,
               k: int) -> tuple[np.ndarray, np.ndarray]:
        for fid, desc in self.queue.pop_ready(frame_id, timestamp):
            self.hash.add(desc)
            self.frame_ids.append(fid)
        ids = np.asarray(self.frame_ids, np.int64)
        sims = self.hash.query(entry).astype(np.float32)
        self.source.set(frame_id, ids, sims)
        order = np.lexsort((ids, -sims))  # best first; ties: older keyframe first
        return sims[order], ids[order]

    def insert(self, frame_id: int, entry: np.ndarray, timestamp: float | None) -> None:
        self.queue.push(frame_id, timestamp, entry)

    def undo(self, frame_id: int) -> None:
        self.source.drop(frame_id)

    def __len__(self) -> int:
        return self.hash.n_images + len(self.queue)


def create_places(descriptor: GlobalDescriptor, whitening: Whitening | None, conf: dict[str, Any],
                  stream_fit: int | None = None) -> Places:
    """The place memory for ``descriptor`` (by its ``searched_by``), configured by the detector's resolved conf;
    ``stream_fit``: without a whitening, fit one on the first this many keyframes (codes compared by cosine only)."""
    kind = PLACES.get(descriptor.searched_by)
    return kind(descriptor, whitening, conf, stream_fit) if stream_fit is not None else kind(descriptor, whitening, conf)
