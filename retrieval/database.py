"""The keyframe database, persisted in HDF5: what a detector has seen, so a run can resume or be inspected.

Layout (``format_version`` 4)::

    /                       attrs: format_version, conf (JSON), descriptor (weights identity), software, created
    /keyframes/<id:08d>/    one group per keyframe, visible only once fully written
        code         (D,)       float32, unit norm (cosine descriptors: CAE, baselines), or
                     (n, 32)    uint8 binary descriptors (hashed descriptors: MILD's ORB)
        keypoints    (N, 2)     float32, original-image pixels
        descriptors  (N, F)     uint8 when lossless (SIFT), else the extractor's dtype
        scales       (N,)       float32
        candidates   (k, 6)     float64 rows (CANDIDATE_ROW: frame id, cosine score, matches, inliers, temporal score,
                                confidence) of every hypothesis judged
        attrs: frame_id, timestamp, source (file name, bytes), fingerprint ("size:hash" of the file, or ""),
               pose (12 floats, 3x4 row-major, when known), edge_ratio, loop (accepted match frame id, -1 if
               none), descriptor_dtype, metric, checksum (BLAKE2b of everything above)
    /skipped/<id:08d>/      one empty group per frame that is not a keyframe
        attrs: frame_id, reason ("gated" or "unreadable"), source, fingerprint, edge_ratio, message

Append-only. A record is written under a temporary name and renamed when complete, then the file is flushed;
reopening drops a half-written record and resumes after the last complete frame. Every keyframe carries a checksum
that is verified when it is read, so bit flips are reported as damage instead of being used. Free disk space is
checked before each write (HDF5 cannot recover from a write that fails half-way).
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

from core.conf import conf_diff, conf_get
from core.errors import ConfigError, DatabaseError
from verify.features import Features

__all__ = ["FORMAT_VERSION", "CANDIDATE_ROW", "SKIP_REASONS", "MIN_FREE_BYTES", "FeatureStore", "KeyframeRecord", "FrameEntry",
           "KeyframeDatabase"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 4  #: 4: codes may be binary descriptors (MILD)
CANDIDATE_ROW = ("frame_id", "score", "matches", "inliers", "seq_score", "confidence")  #: a stored candidate row
SKIP_REASONS = ("gated", "unreadable")  #: why a frame is not a keyframe
MIN_FREE_BYTES = 64 << 20  #: no record is written with less free space than this on the database's disk
_TMP = ".incomplete"
_READ_ERRORS = (OSError, KeyError, ValueError, RuntimeError, TypeError, IndexError, AttributeError)


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
    code: np.ndarray  #: (D,) float32 code, or (n, 32) uint8 binary descriptors
    features: Features
    timestamp: float | None = None
    pose: np.ndarray | None = None  #: (3, 4) camera-to-world, when known
    source: str = ""  #: where the frame came from (file name), free text
    edge_ratio: float = float("nan")
    candidates: np.ndarray | None = None  #: (k, len(CANDIDATE_ROW)) rows in CANDIDATE_ROW order
    loop: int = -1  #: accepted match, -1 if none
    fingerprint: str = ""  #: "size:hash" of the source file (``core.images.fingerprint``), "" when unknown


@dataclass(frozen=True)
class FrameEntry:
    """One frame the database holds, keyframe or not: what it was made from."""

    frame_id: int
    kind: str  #: "keyframe", "gated" or "unreadable"
    source: str
    fingerprint: str


def _checksum(arrays: list[np.ndarray], attrs: dict[str, Any]) -> str:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    for key in sorted(attrs):
        h.update(key.encode())
        h.update(_canonical(attrs[key]))
    return h.hexdigest()


def _canonical(value: Any) -> bytes:
    """The same bytes for an attribute as written and as HDF5 gives it back (numpy scalars, bytes vs str)."""
    if isinstance(value, (bytes, np.bytes_)):
        return b"b:" + bytes(value)
    if isinstance(value, str):
        return b"s:" + value.encode("utf-8", "surrogateescape")
    if isinstance(value, np.ndarray) and value.dtype.kind not in "biuf":
        return b"a:" + repr(value.tolist()).encode()
    return b"n:" + np.ascontiguousarray(value, np.float64).tobytes()


_CHECKED_ATTRS = ("frame_id", "timestamp", "pose", "edge_ratio", "loop", "descriptor_dtype", "metric", "source",
                  "fingerprint")
_ARRAYS = ("code", "keypoints", "descriptors", "scales", "candidates")


def _file_size_limit() -> float:
    soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    return float("inf") if soft == resource.RLIM_INFINITY else float(soft)


class KeyframeDatabase:
    """Append-only HDF5 store of keyframes (and of the frames that are not).

    Args:
        path: the ``.h5`` file; created when missing, resumed when present.
        conf: the resolved detector conf, saved in a new file and compared with an existing one.
        encoder: identity of the global descriptor (weights hash); an existing file made with another is refused.
        flush_every: flush to disk after this many records (1 = a killed run loses nothing).
        mode: ``"a"`` create or resume, ``"r"`` read only.

    Raises:
        DatabaseError: the file is damaged (e.g. truncated), locked by another process, or not accessible.
        ConfigError: of another format version, not a keyframe database, or made with another conf or other
            weights. The file is never modified in these cases.
    """

    def __init__(self, path: str | Path, conf: dict[str, Any] | None = None, encoder: str = "",
                 flush_every: int = 1, mode: str = "a") -> None:
        self.path = Path(path)
        self.flush_every = max(1, int(flush_every))
        self._since_flush = 0
        self._broken = False
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
                self._ensure_space()
                self.file.attrs.update({"format_version": FORMAT_VERSION, "conf": json.dumps(conf or {}),
                                        "descriptor": encoder, "software": "cae-loop-closure",
                                        "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
                self.file.require_group("keyframes")
                self.file.require_group("skipped")
                self.file.flush()
            if mode != "r":
                for group in ("keyframes", "skipped"):
                    if f"{group}/{_TMP}" in self.file:
                        log.warning("%s: dropping a half-written record from an interrupted run", self.path)
                        del self.file[f"{group}/{_TMP}"]
        except _READ_ERRORS as err:
            self.file.close()
            if isinstance(err, (ConfigError, DatabaseError)):
                raise
            raise self._damaged(err) from None
        except BaseException:
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
            raise ConfigError(f"{self.path} has format_version {version}; this software reads {FORMAT_VERSION}; "
                              "choose another --out")
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

    def _write_group(self, parent: str, frame_id: int, fill: Any) -> None:
        """Creates ``parent/.incomplete``, lets ``fill(group)`` write it, then renames it to its frame id."""
        if self._broken:
            raise DatabaseError(f"{self.path}: an earlier write failed; nothing more is written")
        self._ensure_space()
        try:
            grp = self.file.create_group(f"{parent}/{_TMP}")
            fill(grp)
            self.file.move(f"{parent}/{_TMP}", f"{parent}/{int(frame_id):08d}")
            self._maybe_flush()
        except (OSError, RuntimeError, ValueError) as err:
            self._broken = True
            raise DatabaseError(f"cannot write {self.path}: {str(err)[:160]}") from None

    def append(self, rec: KeyframeRecord) -> None:
        """Writes one keyframe atomically (temporary group, then rename)."""
        feats = rec.features.compact()
        code = np.asarray(rec.code)
        arrays = {"code": code if code.dtype == np.uint8 and code.ndim == 2 else code.astype(np.float32), "keypoints": feats.keypoints.astype(np.float32),
                  "descriptors": feats.descriptors, "scales": feats.scales.astype(np.float32),
                  "candidates": (np.zeros((0, len(CANDIDATE_ROW))) if rec.candidates is None
                                 else np.asarray(rec.candidates, np.float64)).reshape(-1, len(CANDIDATE_ROW))}
        attrs: dict[str, Any] = {"frame_id": int(rec.frame_id), "source": np.bytes_(_name_bytes(rec.source)),
                                 "fingerprint": rec.fingerprint, "edge_ratio": float(rec.edge_ratio),
                                 "loop": int(rec.loop), "metric": feats.metric,
                                 "descriptor_dtype": np.dtype(rec.features.descriptors.dtype).name}
        if rec.timestamp is not None:
            attrs["timestamp"] = float(rec.timestamp)
        if rec.pose is not None:
            attrs["pose"] = np.asarray(rec.pose, np.float64).reshape(12)
        attrs["checksum"] = _checksum([arrays[k] for k in _ARRAYS], attrs)

        def fill(grp: h5py.Group) -> None:
            for key in _ARRAYS:
                grp.create_dataset(key, data=arrays[key])
            grp.attrs.update(attrs)

        self._write_group("keyframes", rec.frame_id, fill)

    def add_skipped(self, frame_id: int, reason: str, source: str = "", fingerprint: str = "",
                    edge_ratio: float = float("nan"), message: str = "") -> None:
        """Records a frame that is not a keyframe: ``reason`` "gated" (the quality gate) or "unreadable"."""
        if reason not in SKIP_REASONS:
            raise ValueError(f"reason must be one of {SKIP_REASONS}; got {reason!r}")
        attrs = {"frame_id": int(frame_id), "reason": reason, "source": np.bytes_(_name_bytes(source)),
                 "fingerprint": fingerprint, "edge_ratio": float(edge_ratio),
                 "message": message[:300].encode("utf-8", "backslashreplace").decode("utf-8")}  # names not UTF-8
        self._write_group("skipped", frame_id, lambda grp: grp.attrs.update(attrs))

    def add_gated(self, frame_id: int, source: str = "", fingerprint: str = "", edge_ratio: float = float("nan")
                  ) -> None:
        """Records a frame the quality gate rejected."""
        self.add_skipped(frame_id, "gated", source, fingerprint, edge_ratio)

    def _maybe_flush(self) -> None:
        self._since_flush += 1
        if self._since_flush >= self.flush_every:
            self.file.flush()
            self._since_flush = 0

    # ----------------------------------------------------------------------------------------------- reading
    @property
    def conf(self) -> dict[str, Any]:
        return json.loads(self.file.attrs["conf"])

    @property
    def encoder(self) -> str:
        """Identity of the global descriptor the codes were made with."""
        return str(self.file.attrs.get("descriptor", ""))

    def _names(self, group: str = "keyframes") -> list[str]:
        """Complete records in frame-id order (a half-written one from a killed run is never listed)."""
        try:
            return [n for n in self.file[group] if not n.startswith(".")]
        except _READ_ERRORS as err:
            raise self._damaged(err, group) from None

    def __len__(self) -> int:
        return len(self._names())

    def _skipped(self) -> Iterator[h5py.Group]:
        for name in self._names("skipped"):
            yield self.file["skipped"][name]

    def skipped(self, reason: str | None = None) -> np.ndarray:
        """Frame ids of the frames that are not keyframes (of one ``reason`` when given), ``(n,)`` int64."""
        try:
            ids = [int(g.attrs["frame_id"]) for g in self._skipped() if reason is None or g.attrs["reason"] == reason]
        except _READ_ERRORS as err:
            raise self._damaged(err, "skipped frames") from None
        return np.array(ids, np.int64)

    def gated(self) -> np.ndarray:
        """Frame ids the gate rejected, ``(n,)`` int64."""
        return self.skipped("gated")

    def last_frame_id(self) -> int:
        """The largest frame id stored (keyframe or not), -1 when empty."""
        last = [int(names[-1]) for names in (self._names(), self._names("skipped")) if names]
        return max(last, default=-1)  # groups are listed in name order: zero-padded ids

    def frames(self) -> list[FrameEntry]:
        """Every frame held (keyframes and skipped ones) in frame-id order, with what it was made from."""
        try:
            out = [FrameEntry(int(g.attrs["frame_id"]), "keyframe", _name_str(g.attrs["source"]),
                              str(g.attrs.get("fingerprint", "")))
                   for g in (self.file["keyframes"][n] for n in self._names())]
            out += [FrameEntry(int(g.attrs["frame_id"]), str(g.attrs["reason"]), _name_str(g.attrs["source"]),
                               str(g.attrs.get("fingerprint", ""))) for g in self._skipped()]
        except _READ_ERRORS as err:
            raise self._damaged(err, "frame list") from None
        return sorted(out, key=lambda e: e.frame_id)

    def _group(self, name: str) -> tuple[h5py.Group, dict[str, np.ndarray]]:
        """A keyframe group and its arrays, checksum verified."""
        try:
            grp = self.file["keyframes"][name]
            arrays = {k: grp[k][()] for k in _ARRAYS}
            attrs = {k: grp.attrs[k] for k in _CHECKED_ATTRS if k in grp.attrs}
            ok = _checksum([arrays[k] for k in _ARRAYS], attrs) == grp.attrs["checksum"]
        except _READ_ERRORS as err:
            raise self._damaged(err, f"keyframe {name}") from None
        if not ok:
            raise DatabaseError(f"{self.path} is damaged: keyframe {int(name)} fails its checksum; the files written "
                                "from it are left as they were; move it away to start again")
        return grp, arrays

    def _features(self, grp: h5py.Group, arrays: dict[str, np.ndarray]) -> Features:
        desc = arrays["descriptors"].astype(grp.attrs["descriptor_dtype"], copy=False)
        return Features(arrays["keypoints"], desc, arrays["scales"], str(grp.attrs["metric"]))

    def features(self, frame_id: int) -> Features:
        """One keyframe's local features (descriptors in the extractor's dtype).

        Raises:
            KeyError: no complete keyframe with that id.
            DatabaseError: it is damaged.
        """
        name = f"{int(frame_id):08d}"
        if name not in self.file["keyframes"]:
            raise KeyError(frame_id)
        return self._features(*self._group(name))

    def __iter__(self) -> Iterator[KeyframeRecord]:
        """Keyframes in frame-id order."""
        for name in self._names():
            grp, arrays = self._group(name)
            a = grp.attrs
            yield KeyframeRecord(frame_id=int(a["frame_id"]), code=arrays["code"],
                                 features=self._features(grp, arrays),
                                 timestamp=float(a["timestamp"]) if "timestamp" in a else None,
                                 pose=np.asarray(a["pose"]).reshape(3, 4) if "pose" in a else None,
                                 source=_name_str(a["source"]), edge_ratio=float(a["edge_ratio"]),
                                 candidates=arrays["candidates"], loop=int(a["loop"]),
                                 fingerprint=str(a.get("fingerprint", "")))

    def search_entries(self) -> Iterator[tuple[int, np.ndarray, float | None, Features]]:
        """``(frame_id, code, timestamp, features)`` per keyframe in frame-id order, checksums verified."""
        for name in self._names():
            grp, arrays = self._group(name)
            ts = grp.attrs.get("timestamp")
            yield (int(grp.attrs["frame_id"]), arrays["code"], None if ts is None else float(ts),
                   self._features(grp, arrays))

    def results(self) -> Iterator[tuple[int, np.ndarray, int]]:
        """``(frame_id, candidates (k, len(CANDIDATE_ROW)), loop)`` per keyframe in frame-id order, checksums verified."""
        for name in self._names():
            grp, arrays = self._group(name)
            yield int(grp.attrs["frame_id"]), arrays["candidates"], int(grp.attrs["loop"])

    def poses(self) -> np.ndarray:
        """``(n, 3, 4)`` camera-to-world pose per keyframe in frame-id order, NaN where none was given."""
        out = [np.full((3, 4), np.nan) if rec.pose is None else rec.pose for rec in self]
        return np.stack(out).astype(np.float64) if out else np.zeros((0, 3, 4))

    def codes(self) -> tuple[np.ndarray, np.ndarray]:
        """All codes, ``(n, D)`` float32, with their frame ids ``(n,)``; ``(0, 0)`` and ``(0,)`` when the keyframes
        hold binary descriptors (MILD) instead of codes."""
        entries = [(fid, code) for fid, code, _, _ in self.search_entries() if code.ndim == 1]
        if not entries:
            return np.zeros((0, 0), np.float32), np.zeros(0, np.int64)
        return np.stack([c for _, c in entries]), np.array([f for f, _ in entries], np.int64)

    def close(self) -> None:
        """Flushes and closes the file (after a failed write only closes: HDF5 cannot flush a broken file)."""
        if self.file.id.valid:
            if not self._broken:
                self.file.flush()
                self.file.close()

    def __enter__(self) -> "KeyframeDatabase":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
