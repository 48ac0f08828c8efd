"""The keyframe store, persisted in one HDF5 file: what a detector has seen, so a run can resume or be inspected.

Built for millions of keyframes: append-only and columnar, every column one chunked, resizable dataset (no group
per keyframe). Layout (``format_version`` 8)::

    /                 attrs: format_version, conf (JSON), descriptor (weights identity), software, created,
                      committed (frames visible: the commit point, written last)
    /frames/          one row per frame, keyframe or not, in frame-id order
        frame_id      (n,)     int64
        kind          (n,)     uint8: 0 keyframe, 1 gated, 2 unreadable (KINDS)
        timestamp     (n,)     float64, NaN when unknown
        pose          (n, 12)  float64, 3x4 camera-to-world row-major, NaN when unknown
        edge_ratio    (n,)     float64
        loop          (n,)     int64 accepted match frame id, -1 if none
        source, fingerprint, message   (n,) variable-length strings (source as bytes: any file name survives)
        code_end, feat_end, cand_end, image_end   (n,) int64: end offsets into the ragged arrays below (start = the
                                        previous row's end; a skipped frame adds nothing)
        feat_checksum (n,)     BLAKE2b-128 of the row's local features and grey copy (verified when they are read)
    /blocks/end, /blocks/checksum      per written block of rows (``flush_every`` frames): its end row and one
                               BLAKE2b-128 of its rows, codes and candidates (verified on the first read)
    /codes            (R, D)   the searched code, float16 (whitened and unit-norm: what the index holds), one row a
                               keyframe; or (R, 32) uint8 binary descriptors, several rows a keyframe (MILD); where
                               the detector calibrates itself on the stream (``retrieval.online``), the raw code
                               (float16, what it searched is made from it: a refit moves every keyframe into a new
                               whitening)
    /features/keypoints   (M, 2) uint16, x and y in 1/8 pixel (``verify.features.KEYPOINT_STEP``)
    /features/descriptors (M, F) uint8 when lossless (SIFT), else the extractor's dtype; gzip-compressed
    /features/scales      (M,)   float16
    /candidates       (C, 6)   float64 rows (CANDIDATE_ROW) of every hypothesis judged
    /images           (B,)     uint8: each keyframe's grey copy (``retrieval.feature_jobs.grey_copy``), where it
                               keeps one instead of its features (a stream: ``runtime.features: image``)
    /online/<frame_id>/        the online calibration's state after that keyframe (``LoopDetector._save_online``),
                               written at each refit, beside the blocks: attrs ``meta`` (JSON) and ``checksum``
                               (BLAKE2b-128 of meta and arrays, written last: a state without it is half-written and
                               never read), one dataset an array; a resumed run takes the newest one its stored
                               keyframes reach (``online_state``)

Beside the file: the write-ahead log (``keyframes.h5.log``) and, where the detector's place index is costly to
rebuild, a copy of it saved on close (``keyframes.h5.index``, ``INDEX_SUFFIX``; ``retrieval.index.KeyframeIndex.save``).

Local features are stored only where the detector cannot have them again (``LoopDetector``: offline, a keyframe's
file gives them again; an empty span then). A frame goes first to the write-ahead log beside the file
(``keyframes.h5.log``, ``retrieval.wal``: one write, durable once ``append`` returns), and ``flush_every`` frames at
a time into the columns: ragged arrays past their committed ends, then the rows and the block's checksum, then
``committed`` raised and the file flushed, then the log emptied. Nothing past the committed ends is ever read, so
a block half-written by a killed run is invisible and overwritten when the run resumes, and the frames of the log
that the columns lack are taken back (a torn last record is dropped). Bit flips are reported as damage instead of
being used. Free disk space is checked before each write (HDF5 cannot recover from a write that fails half-way).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import resource
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from cae_lcd.core.conf import conf_diff, conf_get
from cae_lcd.core.errors import ConfigError, DatabaseError, printable
from verify.features import KEYPOINT_STEP, Features

from .wal import FrameLog, read_records

__all__ = ["FORMAT_VERSION", "CANDIDATE_ROW", "SKIP_REASONS", "KINDS", "MIN_FREE_BYTES", "CHUNK_ROWS",
           "FeatureStore", "KeyframeRecord", "FrameEntry", "KeyframeDatabase"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 8  #: 8: 7 + the online calibration's state (``online/``; its stores keep raw codes); 7: 6 + a grey
#: copy per keyframe (``images``); 6: 5 (columnar, float16 searched codes, compact features) + write-ahead log,
#: features only where a frame cannot be read again
CANDIDATE_ROW = ("frame_id", "score", "matches", "inliers", "seq_score", "confidence")  #: a stored candidate row
SKIP_REASONS = ("gated", "unreadable")  #: why a frame is not a keyframe
KINDS = ("keyframe",) + SKIP_REASONS  #: ``frames/kind`` values, by position
MIN_FREE_BYTES = 64 << 20  #: no record is written with less free space than this on the database's disk
CHUNK_ROWS = 1024  #: HDF5 chunk length of the per-frame columns (rows); ragged arrays use chunks of similar bytes
_READ_ERRORS = (OSError, KeyError, ValueError, RuntimeError, TypeError, IndexError, AttributeError)
_STR = h5py.string_dtype("utf-8")
_BYTES = h5py.string_dtype("ascii")  # bytes in, bytes out: file names that are not UTF-8 survive
#: the per-frame columns: dtype and trailing shape
_COLUMNS: dict[str, tuple[Any, tuple[int, ...]]] = {
    "frame_id": (np.int64, ()), "kind": (np.uint8, ()), "timestamp": (np.float64, ()), "pose": (np.float64, (12,)),
    "edge_ratio": (np.float64, ()), "loop": (np.int64, ()), "source": (_BYTES, ()), "fingerprint": (_STR, ()),
    "message": (_STR, ()), "code_end": (np.int64, ()), "feat_end": (np.int64, ()), "cand_end": (np.int64, ()),
    "image_end": (np.int64, ()), "feat_checksum": ("S32", ())}
_ROW_CHECKED = ("frame_id", "kind", "timestamp", "pose", "edge_ratio", "loop", "source", "fingerprint", "message",
                "code_end", "feat_end", "cand_end", "image_end")
_FEATURES = ("keypoints", "descriptors", "scales")
_STORED = (*_FEATURES, "image")  # a keyframe's features and grey copy: one checksum (``feat_checksum``)
_LOGGED = ("frame_id", "kind", "timestamp", "edge_ratio", "loop", "fingerprint", "message")  # as JSON in the log
LOG_SUFFIX = ".log"  #: the write-ahead log is the store's path plus this (``keyframes.h5.log``)
INDEX_SUFFIX = ".index"  #: the place index saved on close is the store's path plus this (``keyframes.h5.index``)


def _name_bytes(name: str) -> bytes:
    """A file name as bytes (names that are not UTF-8 survive: ``os.fsencode`` undoes surrogate escapes)."""
    return os.fsencode(name)


def _name_str(value: Any) -> str:
    return os.fsdecode(bytes(value)) if isinstance(value, (bytes, np.bytes_)) else str(value)


class FeatureStore:
    """Keyframe features for verification: all kept in memory, or read back from the database on demand.

    Args:
        db: None keeps every keyframe's features in memory (uint8 descriptors, ~64 kB a keyframe for 500 SIFT);
            a database makes memory bounded: features are read from it, the ``cache_size`` most recent kept.
        cache_size: features kept in memory in database mode (least recently used dropped first).
    """

    def __init__(self, db: "KeyframeDatabase | None" = None, cache_size: int = 512) -> None:
        self.db = db
        self.cache_size = max(1, int(cache_size))
        self._items: OrderedDict[int, Features] = OrderedDict()

    def __setitem__(self, frame_id: int, features: Features) -> None:
        self._items[frame_id] = features.compact()
        self._items.move_to_end(frame_id)
        if self.db is not None and len(self._items) > self.cache_size:
            self._items.popitem(last=False)

    def __getitem__(self, frame_id: int) -> Features:
        feats = self._items.get(frame_id)
        if feats is None:
            if self.db is None:
                raise KeyError(frame_id)
            feats = self.db.features(frame_id)
            self[frame_id] = feats
        else:
            self._items.move_to_end(frame_id)
        return feats

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class KeyframeRecord:
    frame_id: int
    code: np.ndarray  #: (D,) the searched code (stored as float16; (r, D / r) float: as r rows), or (n, 32) uint8
    #                    binary descriptors
    features: Features
    timestamp: float | None = None
    pose: np.ndarray | None = None  #: (3, 4) camera-to-world, when known
    source: str = ""  #: where the frame came from (file name), free text
    edge_ratio: float = float("nan")
    candidates: np.ndarray | None = None  #: (k, len(CANDIDATE_ROW)) rows in CANDIDATE_ROW order
    loop: int = -1  #: accepted match, -1 if none
    fingerprint: str = ""  #: "size:hash" of the source file (``cae_lcd.core.images.fingerprint``), "" when unknown
    image: bytes = b""  #: its grey copy (``retrieval.feature_jobs.grey_copy``) when it keeps one, else b""


@dataclass(frozen=True)
class FrameEntry:
    """One frame the database holds, keyframe or not: what it was made from."""

    frame_id: int
    kind: str  #: "keyframe", "gated" or "unreadable"
    source: str
    fingerprint: str


#: the fixed-width part of a frame row, as its checksum reads it
_FIXED = np.dtype([("frame_id", "<i8"), ("kind", "u1"), ("timestamp", "<f8"), ("pose", "<f8", (12,)),
                   ("edge_ratio", "<f8"), ("loop", "<i8"), ("code_end", "<i8"), ("feat_end", "<i8"),
                   ("cand_end", "<i8"), ("image_end", "<i8")])
_TEXT = ("source", "fingerprint", "message")


def _fixed_rows(cols: dict[str, Any]) -> np.ndarray:
    """``(n, itemsize)`` uint8: the fixed-width fields of ``n`` rows, packed (one checksum input a row)."""
    n = len(cols["frame_id"])
    rec = np.zeros(n, _FIXED)
    for key in _FIXED.names:
        rec[key] = np.asarray(cols[key]).reshape(rec[key].shape)
    return rec.view(np.uint8).reshape(n, -1)


def _checksum(fixed: bytes, texts: list[Any], arrays: list[np.ndarray]) -> bytes:
    """BLAKE2b-128 (hex, 32 bytes) of a row's fixed fields, its texts (bytes or str) and arrays' bytes (an empty
    array counts as nothing: it reads back in the dataset's dtype, or as none before the dataset exists)."""
    h = hashlib.blake2b(fixed, digest_size=16)
    encoded = [t if isinstance(t, bytes) else str(t).encode("utf-8", "surrogateescape") for t in texts]
    h.update(b"".join(len(b).to_bytes(4, "little") + b for b in encoded))
    for a in arrays:
        if a.size:
            h.update(str(a.shape[1:]).encode() + np.ascontiguousarray(a).tobytes())
    return h.hexdigest().encode()


def _block_checksum(cols: dict[str, Any], codes: np.ndarray, cands: np.ndarray) -> bytes:
    """The one checksum of a written block: its rows' checked fields, texts, codes and candidates."""
    texts = [t for k in _TEXT for t in cols[k]]
    return _checksum(_fixed_rows(cols).tobytes(), texts, [np.asarray(codes), np.asarray(cands)])


def _grow(ds: h5py.Dataset, size: int) -> None:
    """Makes ``ds`` hold at least ``size`` rows, growing by a quarter (at least a chunk) at a time so that appends
    rarely resize (rows past the committed ends are unused: HDF5 allocates no disk for chunks never written)."""
    if len(ds) < size:
        ds.resize(max(size, len(ds) + max(ds.chunks[0], len(ds) // 4)), axis=0)


def _append_one(view: np.ndarray, value: Any) -> np.ndarray:
    """``view`` with ``value`` appended, as a view of a buffer that doubles when full (``np.append`` copied the
    whole column on every frame: quadratic in the map's size)."""
    n, base = len(view), view.base
    if not isinstance(base, np.ndarray) or base.base is not None or base.ndim != 1 or len(base) <= n \
            or base.dtype != view.dtype or n and not np.shares_memory(base[n - 1:n], view[n - 1:n]):
        base = np.empty(max(64, 2 * n), view.dtype)
        base[:n] = view
    base[n] = value
    return base[:n + 1]


def _file_size_limit() -> float:
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return float("inf") if soft == resource.RLIM_INFINITY else float(soft)


def _pack_features(feats: Features, image: bytes = b"") -> dict[str, np.ndarray]:
    """Features (compacted) as stored: keypoints in 1/KEYPOINT_STEP pixel (uint16), float16 scales; and the grey
    copy as uint8."""
    kp = np.clip(np.round(np.asarray(feats.keypoints, np.float64) * KEYPOINT_STEP), 0, 65535).astype(np.uint16)
    return {"keypoints": kp.reshape(-1, 2), "descriptors": feats.descriptors,
            "scales": np.asarray(feats.scales, np.float16).reshape(-1), "image": np.frombuffer(image, np.uint8)}


class KeyframeDatabase:
    """Append-only, columnar HDF5 store of keyframes (and of the frames that are not); see the module doc.

    Args:
        path: the ``.h5`` file; created when missing, resumed when present.
        conf: the resolved detector conf, saved in a new file and compared with an existing one.
        encoder: identity of the global descriptor (weights hash); an existing file made with another is refused.
        flush_every: frames moved from the write-ahead log into the columns at a time (every frame is in the log
            when ``append`` returns, so a killed run loses nothing whatever this is; a larger block is cheaper).
        mode: ``"a"`` create or resume, ``"r"`` read only.

    Raises:
        DatabaseError: the file is damaged (e.g. truncated), locked by another process, or not accessible.
        ConfigError: of another format version, not a keyframe database, or made with another conf or other
            weights. The file is never modified in these cases.
    """

    def __init__(self, path: str | Path, conf: dict[str, Any] | None = None, encoder: str = "",
                 flush_every: int = 256, mode: str = "a") -> None:
        self.path = Path(path)
        self.flush_every = max(1, int(flush_every))
        self._log: FrameLog | None = None
        self._pending: list[tuple[dict[str, Any], dict[str, np.ndarray], dict[str, np.ndarray], dict[str, str]]] = []
        self._broken = False
        self._verified_blocks: set[int] = set()  # written blocks whose checksum held (or written here)
        self._handles: dict[str, h5py.Dataset] = {}
        exists = self.path.exists()
        if exists and not self.path.is_file():
            raise ConfigError(f"{self.path} exists and is not a file; choose another --out")
        self.file = self._open(mode)
        try:
            if exists and "format_version" in self.file.attrs:
                self._check(conf, encoder)
            elif mode == "r":
                raise ConfigError(f"{self.path} is not a keyframe database (no format_version)")
            elif exists and len(self.file.keys()) > 0:
                raise ConfigError(f"{self.path} is an HDF5 file but not a keyframe database; choose another --out")
            else:
                self._create(conf, encoder)
            self._load_columns(mode)
            if mode != "r":  # last: a refused file is left as it was, its log too
                self._log = FrameLog(self.path.with_name(self.path.name + LOG_SUFFIX))
                self._replay()
        except _READ_ERRORS as err:
            self._close_log()
            self.file.close()
            if isinstance(err, (ConfigError, DatabaseError)):
                raise
            raise self._damaged(err) from None
        except BaseException:
            self._close_log()
            self.file.close()
            raise

    # ----------------------------------------------------------------------------------------------- opening
    def _open(self, mode: str) -> h5py.File:
        if mode == "r" and not self.path.exists():
            raise ConfigError(f"keyframe database not found: {self.path}")
        try:
            return h5py.File(self.path, "r" if mode == "r" else "a")
        except OSError as err:
            text = str(err)
            if "unable to lock file" in text or err.errno == 11:
                raise DatabaseError(f"{self.path} is in use by another process (another run into the same --out?); "
                                    "wait for it to finish or choose another --out") from None
            if "ermission denied" in text or (self.path.exists() and not os.access(self.path, os.R_OK | os.W_OK)):
                raise DatabaseError(f"cannot open {self.path}: permission denied") from None
            if "No such file" in text or "ead-only" in text or "not permitted" in text:
                raise DatabaseError(f"cannot create {self.path}: {text.split(';')[0].split('(')[0].strip()}") \
                    from None
            raise DatabaseError(f"{self.path} is damaged (truncated or corrupt: {text.split(';')[0][:120]}); move "
                                "it away to start again, or choose another --out") from None

    def _damaged(self, err: BaseException, what: str = "") -> DatabaseError:
        where = f" ({what})" if what else ""
        return DatabaseError(f"{self.path} is damaged{where}: {type(err).__name__}: {str(err)[:160]}; the files "
                             "written from it are left as they were; move it away to start again")

    def _check(self, conf: dict[str, Any] | None, encoder: str) -> None:
        version = int(self.file.attrs["format_version"])
        if version != FORMAT_VERSION:
            raise ConfigError(f"{self.path} has format_version {version}; this software reads {FORMAT_VERSION} "
                              "(older keyframe stores are not converted): choose another --out")
        stored = json.loads(self.file.attrs["conf"])
        given = json.loads(json.dumps(conf))
        if conf is not None and stored != given:
            keys = ", ".join(f"{k} ({conf_get(stored, k)!r} there, {conf_get(given, k)!r} now)"
                             for k in conf_diff(stored, given))
            raise ConfigError(f"{self.path} was written with a different configuration: {keys}; resume with the "
                              "same settings, or choose another --out")
        if encoder and self.encoder and self.encoder != encoder:
            raise ConfigError(f"{self.path} was written with another global descriptor or other weights "
                              f"({self.encoder}); resume with the same --weights, or choose another --out")

    def _create(self, conf: dict[str, Any] | None, encoder: str) -> None:
        """Writes the header and the empty per-frame columns (the ragged arrays come with the first keyframe)."""
        self._ensure_space()
        frames = self.file.require_group("frames")
        for key, (dtype, tail) in _COLUMNS.items():
            frames.create_dataset(key, shape=(0, *tail), maxshape=(None, *tail), dtype=dtype,
                                  chunks=(CHUNK_ROWS, *tail))
        blocks = self.file.require_group("blocks")
        for key, dtype in (("end", np.int64), ("checksum", "S32")):
            blocks.create_dataset(key, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(CHUNK_ROWS,))
        self.file.attrs.update({"format_version": FORMAT_VERSION, "conf": json.dumps(conf or {}),
                                "descriptor": encoder, "software": "cae-loop-closure", "committed": 0,
                                "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
        self.file.flush()

    def _load_columns(self, mode: str) -> None:
        """Reads the small per-frame columns into memory (``committed`` rows). Whatever lies past the committed
        ends (a frame half-written by a killed run, or room reserved for growth) is never read, and overwritten by
        the next append."""
        n = int(self.file.attrs["committed"])
        frames = self.file["frames"]
        self._cols = {k: frames[k][:n] for k in ("frame_id", "kind", "code_end", "feat_end", "cand_end", "image_end")}
        if len(self._cols["frame_id"]) != n:
            raise DatabaseError(f"{self.path} is damaged: {len(self._cols['frame_id'])} frame rows, {n} committed; "
                                "move it away to start again")
        self._kf_rows = np.flatnonzero(self._cols["kind"] == 0)
        self._h5_rows = n
        ends = self.file["blocks/end"][:]  # the committed blocks: up to the one ending at row n (room past it)
        last = np.flatnonzero(ends == n)[:1] if n else np.zeros(1, np.int64) - 1
        if not len(last):
            raise DatabaseError(f"{self.path} is damaged: no block ends at its {n} committed rows; move it away to "
                                "start again")
        self._block_ends = ends[:int(last[0]) + 1].astype(np.int64)
        if mode != "r" and len(frames["frame_id"]) > n and frames["frame_id"][n] > self.last_frame_id():
            log.warning("%s: a half-written frame from an interrupted run is dropped (overwritten)", self.path)

    def _end(self, column: str) -> int:
        return int(self._cols[column][-1]) if len(self._cols[column]) else 0

    # ----------------------------------------------------------------------------------------------- writing
    def _ensure_space(self) -> None:
        """Refuses to write when the disk (or the file-size limit) leaves less than ``MIN_FREE_BYTES``."""
        try:
            st = os.statvfs(self.path.parent)
            free = float(st.f_bavail) * st.f_frsize
        except OSError:
            free = float("inf")
        size = self.path.stat().st_size if self.path.exists() else 0
        free = min(free, _file_size_limit() - size)
        if free < MIN_FREE_BYTES:
            raise DatabaseError(f"not enough space to write {self.path}: {max(free, 0) / 2**20:.0f} MiB left (need "
                                f"{MIN_FREE_BYTES >> 20} MiB); everything written so far is kept: free space and run "
                                "again to resume")

    def _ds(self, name: str) -> h5py.Dataset:
        """A dataset handle, looked up once (HDF5 path lookups cost more than the small writes of an append)."""
        ds = self._handles.get(name)
        if ds is None:
            ds = self._handles[name] = self.file[name]
        return ds

    def _ragged(self, name: str, rows: np.ndarray) -> h5py.Dataset:
        """The ragged dataset ``name``, created for ``rows``' dtype and width on first use."""
        if name in self._handles or name in self.file:
            ds = self._ds(name)
            if ds.shape[1:] != rows.shape[1:]:
                raise ConfigError(f"{self.path}: {name} rows have shape {ds.shape[1:]}; got {rows.shape[1:]}")
            return ds
        tail = rows.shape[1:]
        chunk = max(64, (1 << 16) // max(1, rows.dtype.itemsize * int(np.prod(tail))))
        compress = {"compression": "gzip", "compression_opts": 4, "shuffle": True} \
            if name == "features/descriptors" else {}
        return self.file.create_dataset(name, shape=(0, *tail), maxshape=(None, *tail), dtype=rows.dtype,
                                        chunks=(chunk, *tail), **compress)

    def _extend(self, name: str, rows: np.ndarray, start: int) -> int:
        """Writes ``rows`` at ``start`` of the ragged dataset ``name``; returns the new end."""
        if len(rows) == 0:
            return start
        ds = self._ragged(name, rows)
        _grow(ds, start + len(rows))
        ds[start:start + len(rows)] = rows.astype(ds.dtype, copy=False)
        return start + len(rows)

    def _append_row(self, row: dict[str, Any], ragged: dict[str, np.ndarray], features: dict[str, np.ndarray],
                    attrs: dict[str, str] | None = None) -> None:
        """Appends one frame to the write-ahead log (durable once this returns), then keeps it pending; every
        ``flush_every`` frames the pending ones move into the columns (``_write_block``)."""
        if self._broken:
            raise DatabaseError(f"{self.path}: an earlier write failed; nothing more is written")
        self._ensure_space()
        try:
            self._log.append({**{k: row[k] for k in _LOGGED}, "source": bytes(row["source"]).hex(),
                              "attrs": attrs or {}},
                             {"pose": np.asarray(row["pose"], np.float64), **ragged, **features})
        except OSError as err:
            self._broken = True
            raise DatabaseError(f"cannot write {self._log.path}: {str(err)[:160]}") from None
        self._remember(row, ragged, features, attrs or {})
        if attrs:  # once per store (the first keyframe with features): what pending features are read back with
            self.file.attrs.update(attrs)
        if len(self._pending) >= self.flush_every:
            self._write_block()

    def _remember(self, row: dict[str, Any], ragged: dict[str, np.ndarray], features: dict[str, np.ndarray],
                  attrs: dict[str, str]) -> None:
        """Makes a logged frame visible (in-memory columns, offsets) and pending for the next block."""
        row["code_end"] = self._end("code_end") + len(ragged["codes"])
        row["cand_end"] = self._end("cand_end") + len(ragged["candidates"])
        row["feat_end"] = self._end("feat_end") + len(features["keypoints"])
        row["image_end"] = self._end("image_end") + len(features["image"])
        n = len(self._cols["frame_id"])
        for key in ("frame_id", "kind", "code_end", "feat_end", "cand_end", "image_end"):
            self._cols[key] = _append_one(self._cols[key], row[key])
        if row["kind"] == 0:
            self._kf_rows = _append_one(self._kf_rows, n)
        self._pending.append((row, ragged, features, attrs))

    def _write_block(self) -> None:
        """Moves the pending frames into the columns: ragged arrays past their committed ends, then the rows, then
        ``committed`` raised and the file flushed (the commit point), then the log emptied."""
        if not self._pending or self._broken:
            return
        self._ensure_space()
        n0, m = self._h5_rows, len(self._pending)
        rows = [p[0] for p in self._pending]
        try:
            for attrs in (p[3] for p in self._pending):
                self.file.attrs.update({k: v for k, v in attrs.items() if k not in self.file.attrs})
            self._extend_all("codes", [p[1]["codes"] for p in self._pending], "code_end", n0)
            self._extend_all("candidates", [p[1]["candidates"] for p in self._pending], "cand_end", n0)
            for key in _FEATURES:
                self._extend_all(f"features/{key}", [p[2][key] for p in self._pending], "feat_end", n0)
            self._extend_all("images", [p[2]["image"] for p in self._pending], "image_end", n0)
            for row, _, feats, _ in self._pending:
                row["feat_checksum"] = _checksum(b"", [], [feats[k] for k in _STORED])
            self._write_block_checksum(rows, [p[1] for p in self._pending], n0 + m)
            for key in _COLUMNS:
                ds = self._ds(f"frames/{key}")
                _grow(ds, n0 + m)
                values = [r[key] for r in rows]
                ds[n0:n0 + m] = np.array(values, dtype=object) if ds.dtype.kind == "O" else np.asarray(values)
            self.file.attrs["committed"] = n0 + m
            self.file.flush()
            self._log.clear()
        except (OSError, RuntimeError, ValueError, TypeError) as err:
            self._broken = True
            raise DatabaseError(f"cannot write {self.path}: {str(err)[:160]}") from None
        self._h5_rows, self._pending = n0 + m, []

    def _write_block_checksum(self, rows: list[dict[str, Any]], ragged: list[dict[str, np.ndarray]], end: int
                              ) -> None:
        """Appends the block's end row and its one checksum (rows, codes and candidates) to ``blocks/``."""
        b = len(self._block_ends)
        cols = {k: [r[k] for r in rows] for k in _ROW_CHECKED}
        arrays = [[a[k] for a in ragged if len(a[k])] for k in ("codes", "candidates")]
        joined = [np.concatenate(parts) if parts else np.zeros((0,)) for parts in arrays]
        for key, value in (("end", end), ("checksum", _block_checksum(cols, *joined))):
            ds = self._ds(f"blocks/{key}")
            _grow(ds, b + 1)
            ds[b] = value
        self._block_ends = _append_one(self._block_ends, end)
        self._verified_blocks.add(b)

    def _extend_all(self, name: str, parts: list[np.ndarray], column: str, n0: int) -> None:
        """Writes the pending rows' ``parts`` of ragged dataset ``name`` in one call, after row ``n0 - 1``'s end."""
        parts = [p for p in parts if len(p)]
        if parts:
            self._extend(name, np.concatenate(parts), int(self._cols[column][n0 - 1]) if n0 else 0)

    def _replay(self) -> None:
        """Takes back the frames of the write-ahead log that the columns do not hold yet (a run killed between
        two blocks), and writes them into the columns."""
        last, n = self.last_frame_id(), 0
        for meta, arrays in read_records(self._log.path):
            if meta["frame_id"] <= last:
                continue  # moved into the columns before the kill
            row = {k: meta[k] for k in _LOGGED}
            row.update({"source": bytes.fromhex(meta["source"]), "pose": arrays["pose"]})
            self._remember(row, {k: arrays[k] for k in ("codes", "candidates")},
                           {k: arrays[k] for k in _STORED}, meta["attrs"])
            self.file.attrs.update({k: v for k, v in meta["attrs"].items() if k not in self.file.attrs})
            last, n = meta["frame_id"], n + 1
        if n:
            log.info("%s: %d frames taken back from the write-ahead log %s", self.path, n, self._log.path.name)
        self._write_block()
        self._log.clear()  # a torn record of a killed run (never used) goes too

    def _row(self, frame_id: int, kind: int, source: str, fingerprint: str, edge_ratio: float) -> dict[str, Any]:
        if len(self._cols["frame_id"]) and frame_id <= self._cols["frame_id"][-1]:
            raise ConfigError(f"frame id {frame_id} is not after the last frame stored ({self._cols['frame_id'][-1]})")
        return {"frame_id": int(frame_id), "kind": kind, "timestamp": np.nan, "pose": np.full(12, np.nan),
                "edge_ratio": float(edge_ratio), "loop": -1, "source": _name_bytes(source),
                "fingerprint": str(fingerprint), "message": ""}

    def append(self, rec: KeyframeRecord) -> None:
        """Writes one keyframe atomically (visible once ``committed`` counts it)."""
        feats = rec.features.compact()
        code = np.asarray(rec.code)
        binary = code.dtype == np.uint8 and code.ndim == 2
        row = self._row(rec.frame_id, 0, rec.source, rec.fingerprint, rec.edge_ratio)
        row.update({"loop": int(rec.loop), "timestamp": np.nan if rec.timestamp is None else float(rec.timestamp)})
        if rec.pose is not None:
            row["pose"] = np.asarray(rec.pose, np.float64).reshape(12)
        cands = (np.zeros((0, len(CANDIDATE_ROW))) if rec.candidates is None
                 else np.asarray(rec.candidates, np.float64)).reshape(-1, len(CANDIDATE_ROW))
        rows = code.reshape(-1, code.shape[-1]) if code.ndim == 2 else code.reshape(1, -1)  # a code as rows of the width
        ragged = {"codes": code if binary else rows.astype(np.float16), "candidates": cands}
        attrs = {"metric": feats.metric, "descriptor_dtype": np.dtype(rec.features.descriptors.dtype).name} \
            if len(feats) and "metric" not in self.file.attrs else {}
        self._append_row(row, ragged, _pack_features(feats, rec.image), attrs)

    def add_skipped(self, frame_id: int, reason: str, source: str = "", fingerprint: str = "",
                    edge_ratio: float = float("nan"), message: str = "") -> None:
        """Records a frame that is not a keyframe: ``reason`` "gated" (the quality gate) or "unreadable"."""
        if reason not in SKIP_REASONS:
            raise ValueError(f"reason must be one of {SKIP_REASONS}; got {reason!r}")
        row = self._row(frame_id, KINDS.index(reason), source, fingerprint, edge_ratio)
        row["message"] = printable(message[:300])  # names not UTF-8
        empty = {"codes": np.zeros((0, 0)), "candidates": np.zeros((0, len(CANDIDATE_ROW)))}
        self._append_row(row, empty, _pack_features(Features.empty()))

    def add_gated(self, frame_id: int, source: str = "", fingerprint: str = "", edge_ratio: float = float("nan")
                  ) -> None:
        """Records a frame the quality gate rejected."""
        self.add_skipped(frame_id, "gated", source, fingerprint, edge_ratio)

    # ----------------------------------------------------------------------------------------------- reading
    @property
    def conf(self) -> dict[str, Any]:
        return json.loads(self.file.attrs["conf"])

    @property
    def encoder(self) -> str:
        """Identity of the global descriptor the codes were made with."""
        return str(self.file.attrs.get("descriptor", ""))

    def __len__(self) -> int:
        return len(self._kf_rows)

    def _column(self, key: str, rows: np.ndarray | None = None) -> np.ndarray:
        """Column ``key`` of the rows in the columns (or of ``rows``, sorted positions); strings as ``bytes``
        (source) or ``str``."""
        n = self._h5_rows
        try:
            ds = self._ds(f"frames/{key}")
            if _COLUMNS[key][0] is _STR:
                ds = ds.asstr()
            if rows is None:
                return np.asarray(ds[:n])
            lo = int(rows[0])
            return np.asarray(ds[lo:int(rows[-1]) + 1])[np.asarray(rows) - lo]
        except _READ_ERRORS as err:
            raise self._damaged(err, f"frames/{key}") from None

    def skipped(self, reason: str | None = None) -> np.ndarray:
        """Frame ids of the frames that are not keyframes (of one ``reason`` when given), ``(n,)`` int64."""
        kind = self._cols["kind"]
        sel = kind != 0 if reason is None else kind == KINDS.index(reason)
        return self._cols["frame_id"][sel].astype(np.int64)

    def gated(self) -> np.ndarray:
        """Frame ids the gate rejected, ``(n,)`` int64."""
        return self.skipped("gated")

    @property
    def index_path(self) -> Path:
        """Where the detector saves its place index beside this store (``retrieval.index.KeyframeIndex.save``)."""
        return self.path.with_name(self.path.name + INDEX_SUFFIX)

    def keyframe_ids(self) -> np.ndarray:
        """Frame ids of the keyframes, ``(n,)`` int64 ascending (the frames still only in the log included)."""
        return self._cols["frame_id"][self._kf_rows].astype(np.int64)

    def last_frame_id(self) -> int:
        """The largest frame id stored (keyframe or not), -1 when empty."""
        return int(self._cols["frame_id"][-1]) if len(self._cols["frame_id"]) else -1

    def frames(self) -> list[FrameEntry]:
        """Every frame held (keyframes and skipped ones) in frame-id order, with what it was made from (the frames
        still only in the write-ahead log included; nothing is written: a refused request reads this)."""
        pending = [p[0] for p in self._pending]
        sources = [*self._column("source"), *(r["source"] for r in pending)]
        prints = [*self._column("fingerprint"), *(r["fingerprint"] for r in pending)]
        return [FrameEntry(int(f), KINDS[int(k)], _name_str(s), str(p))
                for f, k, s, p in zip(self._cols["frame_id"], self._cols["kind"], sources, prints)]

    def _span(self, column: str, row: int) -> slice:
        ends = self._cols[column]
        return slice(int(ends[row - 1]) if row else 0, int(ends[row]))

    def _read(self, name: str, span: slice, width: int = 0) -> np.ndarray:
        if name not in self.file:
            return np.zeros((0, width) if width else (0,))
        return self.file[name][span]

    def _block_data(self, b: int, texts: bool) -> dict[str, Any]:
        """All rows of written block ``b``: checked columns (the text ones when asked or not verified yet: they are
        the slow ones to read), codes, candidates; its checksum verified once."""
        lo = int(self._block_ends[b - 1]) if b else 0
        hi = int(self._block_ends[b])
        rows = np.arange(lo, hi)
        texts = texts or b not in self._verified_blocks
        cols = {k: self._column(k, rows) for k in _ROW_CHECKED if texts or k not in _TEXT}
        code_base = int(self._cols["code_end"][lo - 1]) if lo else 0
        cand_base = int(self._cols["cand_end"][lo - 1]) if lo else 0
        try:
            codes = self._read("codes", slice(code_base, int(self._cols["code_end"][hi - 1])), 1)
            cands = self._read("candidates", slice(cand_base, int(self._cols["cand_end"][hi - 1])),
                               len(CANDIDATE_ROW))
            stored = bytes(self.file["blocks/checksum"][b])
        except _READ_ERRORS as err:
            raise self._damaged(err, "codes") from None
        if b not in self._verified_blocks and _block_checksum(cols, codes, cands) != stored:
            raise DatabaseError(f"{self.path} is damaged: frames {int(cols['frame_id'][0])}-{int(cols['frame_id'][-1])}"
                                " fail their checksum; the files written from it are left as they were; move it "
                                "away to start again")
        self._verified_blocks.add(b)
        return {"cols": cols, "codes": codes, "cands": cands, "code_base": code_base, "cand_base": cand_base}

    def _blocks(self, texts: bool = True) -> Iterator[tuple[np.ndarray, dict[str, Any]]]:
        """Keyframe rows block by written block (``flush_every`` frames, one checksum each), each with its verified
        columns (the text ones only when ``texts``), codes and candidates (``cols[k][j]``, ``codes[j]``,
        ``cands[j]`` for the ``j``-th keyframe row)."""
        for b in range(len(self._block_ends)):
            lo = int(self._block_ends[b - 1]) if b else 0
            rows = self._kf_rows[(self._kf_rows >= lo) & (self._kf_rows < int(self._block_ends[b]))]
            if not len(rows):
                continue
            d = self._block_data(b, texts)
            out: dict[str, Any] = {"cols": {k: v[rows - lo] for k, v in d["cols"].items()}}
            for key, column, base in (("codes", "code_end", "code_base"), ("cands", "cand_end", "cand_base")):
                ends = self._cols[column]
                starts = np.where(rows > 0, ends[np.maximum(rows - 1, 0)], 0) - d[base]
                data = d[key] if key == "codes" else d[key].reshape(-1, len(CANDIDATE_ROW))
                out[key] = [data[a:z] for a, z in zip(starts.tolist(), (ends[rows] - d[base]).tolist())]
            yield rows, out

    def _code(self, raw: np.ndarray) -> np.ndarray:
        """A stored code as given back: ``(D,)`` float32 (its rows joined), or ``(n, 32)`` uint8 binary descriptors."""
        return raw.astype(np.float32).reshape(-1) if raw.dtype == np.float16 else raw

    def features(self, frame_id: int) -> Features:
        """One keyframe's local features (descriptors in the extractor's dtype), checksum verified.

        Raises:
            KeyError: no complete keyframe with that id.
            DatabaseError: it is damaged.
        """
        return self._unpack(self._stored_at(self._keyframe_row(frame_id)))

    def image(self, frame_id: int) -> bytes:
        """One keyframe's grey copy (``retrieval.feature_jobs.grey_copy``; b"" when it keeps none), checksum verified.

        Raises:
            KeyError: no complete keyframe with that id.
            DatabaseError: it is damaged.
        """
        return self._stored_at(self._keyframe_row(frame_id))["image"].tobytes()

    def has_image(self, frame_id: int) -> bool:
        """Whether keyframe ``frame_id`` keeps a grey copy (from the in-memory offsets: nothing is read)."""
        try:
            row = self._keyframe_row(frame_id)
        except KeyError:
            return False
        span = self._span("image_end", row)
        return span.stop > span.start

    def _keyframe_row(self, frame_id: int) -> int:
        pos = int(np.searchsorted(self._cols["frame_id"], int(frame_id)))
        if pos >= len(self._cols["frame_id"]) or self._cols["frame_id"][pos] != frame_id \
                or self._cols["kind"][pos] != 0:
            raise KeyError(frame_id)
        return pos

    def _features_at(self, row: int) -> Features:
        return self._unpack(self._stored_at(row))

    def _stored_at(self, row: int) -> dict[str, np.ndarray]:
        """Row ``row``'s packed features and grey copy (``_pack_features``), checksum verified."""
        span = self._span("feat_end", row)
        try:
            if row >= self._h5_rows:  # still pending: as logged (checked when the log was read or written)
                return self._pending[row - self._h5_rows][2]
            packed = {"keypoints": self._read("features/keypoints", span, 2).astype(np.uint16).reshape(-1, 2),
                      "descriptors": self._read("features/descriptors", span, 1),
                      "scales": self._read("features/scales", span).astype(np.float16),
                      "image": self._read("images", self._span("image_end", row)).astype(np.uint8)}
            ok = _checksum(b"", [], [packed[k] for k in _STORED]) == bytes(self.file["frames/feat_checksum"][row])
        except _READ_ERRORS as err:
            raise self._damaged(err, f"features of frame {int(self._cols['frame_id'][row])}") from None
        if not ok:
            raise DatabaseError(f"{self.path} is damaged: the features of keyframe {int(self._cols['frame_id'][row])} "
                                "fail their checksum; the files written from it are left as they were; move it "
                                "away to start again")
        return packed

    def _unpack(self, packed: dict[str, np.ndarray]) -> Features:
        """Stored features (``_pack_features``) as the extractor gave them."""
        if not len(packed["keypoints"]):
            width = self.file["features/descriptors"].shape[1] if "features/descriptors" in self.file else 128
            return Features.empty(width, np.dtype(self.file.attrs.get("descriptor_dtype", "float32")),
                                  str(self.file.attrs.get("metric", "l2")))
        desc = packed["descriptors"].astype(self.file.attrs["descriptor_dtype"], copy=False)
        return Features(packed["keypoints"].astype(np.float32) / KEYPOINT_STEP, desc,
                        packed["scales"].astype(np.float32), str(self.file.attrs["metric"]))

    def __iter__(self) -> Iterator[KeyframeRecord]:
        """Keyframes in frame-id order."""
        self.sync()
        for rows, block in self._blocks():
            c = block["cols"]
            for j, r in enumerate(rows.tolist()):
                ts, pose = float(c["timestamp"][j]), np.asarray(c["pose"][j], np.float64)
                yield KeyframeRecord(frame_id=int(c["frame_id"][j]), code=self._code(block["codes"][j]),
                                     features=self._features_at(r), timestamp=None if np.isnan(ts) else ts,
                                     pose=None if np.isnan(pose).all() else pose.reshape(3, 4),
                                     source=_name_str(c["source"][j]), edge_ratio=float(c["edge_ratio"][j]),
                                     candidates=block["cands"][j], loop=int(c["loop"][j]),
                                     fingerprint=str(c["fingerprint"][j]))

    def search_entries(self, features: bool = True) -> Iterator[tuple[int, np.ndarray, float | None,
                                                                     Features | None]]:
        """``(frame_id, code, timestamp, features)`` per keyframe in frame-id order, checksums verified;
        ``features=False`` reads no local features (None in their place: resuming in database mode)."""
        self.sync()
        for rows, block in self._blocks(texts=False):
            c = block["cols"]
            for j, r in enumerate(rows.tolist()):
                ts = float(c["timestamp"][j])
                yield (int(c["frame_id"][j]), self._code(block["codes"][j]), None if np.isnan(ts) else ts,
                       self._features_at(r) if features else None)

    def results(self) -> Iterator[tuple[int, np.ndarray, int]]:
        """``(frame_id, candidates (k, len(CANDIDATE_ROW)), loop)`` per keyframe in frame-id order, checksums
        verified."""
        self.sync()
        for rows, block in self._blocks(texts=False):
            c = block["cols"]
            for j in range(len(rows)):
                yield int(c["frame_id"][j]), block["cands"][j], int(c["loop"][j])

    def edge_ratios(self) -> np.ndarray:
        """``(n,)`` float64: each keyframe's edge ratio (the gate's), in frame-id order, checksums verified."""
        self.sync()
        out = [block["cols"]["edge_ratio"] for _, block in self._blocks(texts=False)]
        return np.concatenate(out).astype(np.float64) if out else np.zeros(0)

    def write_online(self, frame_id: int, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
        """Writes the online calibration's state after keyframe ``frame_id`` (``online/<frame_id>``, replacing one
        of that id): the arrays, then the checksum (a state without it is never read), then the file flushed.

        Raises:
            DatabaseError: the disk refuses it (nothing more is written to this store).
        """
        if self._broken:
            raise DatabaseError(f"{self.path}: an earlier write failed; nothing more is written")
        self._ensure_space()
        name = f"online/{int(frame_id)}"
        try:
            if name in self.file:
                del self.file[name]
            grp = self.file.require_group("online").create_group(str(int(frame_id)))
            for key, value in arrays.items():
                grp.create_dataset(key, data=np.asarray(value))
            text = json.dumps(meta)
            grp.attrs["meta"] = text
            keys = sorted(arrays)
            grp.attrs["checksum"] = _checksum(text.encode(), keys, [np.asarray(arrays[k]) for k in keys]).decode()
            self.file.flush()
        except (OSError, RuntimeError, ValueError, TypeError) as err:
            self._broken = True
            raise DatabaseError(f"cannot write {self.path}: {str(err)[:160]}") from None

    def online_state(self, last: int) -> tuple[int, dict[str, Any], dict[str, np.ndarray]] | None:
        """The newest complete online state (``write_online``) of a keyframe ``<= last``, as ``(frame_id, meta,
        arrays)``, checksum verified; None when there is none.

        Raises:
            DatabaseError: it is damaged.
        """
        try:
            ids = sorted((int(k) for k in self.file["online"]), reverse=True) if "online" in self.file else []
            for fid in (f for f in ids if f <= last):
                grp = self.file[f"online/{fid}"]
                if "checksum" not in grp.attrs:
                    continue  # half-written by a killed run
                text = str(grp.attrs["meta"])
                arrays = {k: grp[k][()] for k in grp}
                keys = sorted(arrays)
                if _checksum(text.encode(), keys, [np.asarray(arrays[k]) for k in keys]).decode() != \
                        str(grp.attrs["checksum"]):
                    raise DatabaseError(f"{self.path} is damaged: the online calibration state of keyframe {fid} "
                                        "fails its checksum; move it away to start again")
                return fid, json.loads(text), arrays
        except DatabaseError:
            raise
        except _READ_ERRORS as err:
            raise self._damaged(err, "online") from None
        return None

    def poses(self) -> np.ndarray:
        """``(n, 3, 4)`` camera-to-world pose per keyframe in frame-id order, NaN where none was given."""
        self.sync()
        out = [block["cols"]["pose"] for _, block in self._blocks()]
        return np.concatenate(out).reshape(-1, 3, 4).astype(np.float64) if out else np.zeros((0, 3, 4))

    def codes(self) -> tuple[np.ndarray, np.ndarray]:
        """All codes, ``(n, D)`` float32, with their frame ids ``(n,)``; ``(0, 0)`` and ``(0,)`` when the keyframes
        hold binary descriptors (MILD) instead of codes."""
        self.sync()
        if "codes" not in self.file or self.file["codes"].dtype != np.float16:
            return np.zeros((0, 0), np.float32), np.zeros(0, np.int64)
        out = [np.concatenate(block["codes"]) for _, block in self._blocks()]
        return np.concatenate(out).astype(np.float32), self.keyframe_ids()

    def sync(self) -> None:
        """Moves the frames still only in the write-ahead log into the columns now (readers of the columns call it)."""
        if self._pending:
            self._write_block()

    def _close_log(self) -> None:
        if self._log is not None:
            self._log.close(remove=not self._broken)
            self._log = None

    def close(self) -> None:
        """Moves the log into the columns, flushes and closes the file (after a failed write only closes: HDF5
        cannot flush a broken file; the log keeps the frames for the next run)."""
        if self.file.id.valid:
            if not self._broken:
                self.sync()
            if not self._broken:
                self.file.flush()
                self.file.close()
        self._close_log()

    def __enter__(self) -> "KeyframeDatabase":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
