"""The keyframe database, persisted in HDF5: what a detector has seen, so a run can resume or be inspected.

Layout (``format_version`` 1)::

    /                       attrs: format_version, conf (JSON), encoder (weights identity), software, created
    /keyframes/<id:08d>/    one group per keyframe, visible only once fully written
        code         (4096,)    float32, unit norm
        keypoints    (N, 2)     float32, original-image pixels
        descriptors  (N, D)     uint8 when lossless (SIFT), else the extractor's dtype
        scales       (N,)       float32
        candidates   (k, 4)     float64 rows (frame id, cosine score, matches, inliers) of every verified candidate
        attrs: frame_id, timestamp, source, pose (12 floats, 3x4 row-major, when known), edge_ratio,
               loop (accepted match frame id, -1 if none), descriptor_dtype
    /gated                  (n,) int64, frames the quality gate rejected

Append-only. A keyframe is written under a temporary name and renamed when complete, then the file is flushed;
reopening drops a half-written keyframe and resumes after the last complete frame.
"""

from __future__ import annotations

import json
import logging
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import h5py
import numpy as np

from cae.conf import ConfigError
from verify.features import Features

__all__ = ["FORMAT_VERSION", "FeatureStore", "KeyframeRecord", "KeyframeDatabase"]

log = logging.getLogger(__name__)

FORMAT_VERSION = 1
_TMP = "keyframes/.incomplete"


def _diff(a: Any, b: Any, where: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested dicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [d for k in sorted(set(a) | set(b), key=str)
                for d in _diff(a.get(k), b.get(k), f"{where}.{k}" if where else str(k))]
    return [] if a == b else [where]


def _get(conf: dict[str, Any], dotted: str) -> Any:
    for key in dotted.split("."):
        conf = conf.get(key) if isinstance(conf, dict) else None
    return conf


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
    code: np.ndarray  #: (4096,) float32
    features: Features
    timestamp: float | None = None
    pose: np.ndarray | None = None  #: (3, 4) camera-to-world, when known
    source: str = ""
    edge_ratio: float = float("nan")
    candidates: np.ndarray | None = None  #: (k, 4) frame id, score, matches, inliers
    loop: int = -1  #: accepted match, -1 if none


class KeyframeDatabase:
    """Append-only HDF5 store of keyframes.

    Args:
        path: the ``.h5`` file; created when missing, resumed when present.
        conf: the resolved detector conf, saved in a new file and compared with an existing one.
        encoder: identity of the encoder weights; an existing file made with other weights is refused.
        flush_every: flush to disk after this many keyframes (1 = a killed run loses nothing).
        mode: ``"a"`` create or resume, ``"r"`` read only.

    Raises:
        ConfigError: the file is damaged (e.g. truncated), of another format version, or was made with another
            conf or other weights. The file is never modified in that case.
    """

    def __init__(self, path: str | Path, conf: dict[str, Any] | None = None, encoder: str = "",
                 flush_every: int = 1, mode: str = "a") -> None:
        self.path = Path(path)
        self.flush_every = max(1, int(flush_every))
        self._since_flush = 0
        exists = self.path.exists()
        try:
            self.file = h5py.File(self.path, "r" if mode == "r" else "a")
        except OSError as err:
            raise ConfigError(f"cannot open keyframe database {self.path}: {str(err).split(';')[0]} "
                              "(truncated or damaged?); move it away or choose another --out") from None
        try:
            if exists and "format_version" in self.file.attrs:
                self._check(conf, encoder)
            elif mode == "r":
                raise ConfigError(f"{self.path} is not a keyframe database (no format_version)")
            elif exists and len(self.file.keys()) > 0:
                raise ConfigError(f"{self.path} is an HDF5 file but not a keyframe database; choose another --out")
            else:
                self.file.attrs.update({"format_version": FORMAT_VERSION, "conf": json.dumps(conf or {}),
                                        "encoder": encoder, "software": "cae-loop-closure",
                                        "created": time.strftime("%Y-%m-%dT%H:%M:%S")})
                self.file.require_group("keyframes")
                self.file.create_dataset("gated", shape=(0,), maxshape=(None,), dtype="i8", chunks=(1024,))
                self.file.flush()
            if mode != "r" and _TMP in self.file:
                log.warning("%s: dropping a half-written keyframe from an interrupted run", self.path)
                del self.file[_TMP]
        except BaseException:
            self.file.close()
            raise

    def _check(self, conf: dict[str, Any] | None, encoder: str) -> None:
        version = int(self.file.attrs["format_version"])
        if version != FORMAT_VERSION:
            raise ConfigError(f"{self.path} has format_version {version}; this software reads {FORMAT_VERSION}")
        stored, given = json.loads(self.file.attrs["conf"]), json.loads(json.dumps(conf))
        if conf is not None and stored != given:
            keys = ", ".join(f"{k} ({_get(stored, k)!r} there, {_get(given, k)!r} now)" for k in _diff(stored, given))
            raise ConfigError(f"{self.path} was written with a different configuration: {keys}; resume with the "
                              "same settings, or choose another --out")
        if encoder and self.file.attrs["encoder"] and self.file.attrs["encoder"] != encoder:
            raise ConfigError(f"{self.path} was written with other encoder weights ({self.file.attrs['encoder']}); "
                              "resume with the same --weights, or choose another --out")

    # ----------------------------------------------------------------------------------------------- writing
    def append(self, rec: KeyframeRecord) -> None:
        """Writes one keyframe atomically (temporary group, then rename)."""
        grp = self.file.create_group(_TMP)
        grp.create_dataset("code", data=np.asarray(rec.code, np.float32))
        feats = rec.features
        grp.create_dataset("keypoints", data=feats.keypoints.astype(np.float32))
        grp.create_dataset("descriptors", data=feats.compact().descriptors)
        grp.create_dataset("scales", data=feats.scales.astype(np.float32))
        cands = np.zeros((0, 4)) if rec.candidates is None else np.asarray(rec.candidates, np.float64)
        grp.create_dataset("candidates", data=cands.reshape(-1, 4))
        attrs = {"frame_id": int(rec.frame_id), "source": rec.source, "edge_ratio": float(rec.edge_ratio),
                 "loop": int(rec.loop), "descriptor_dtype": np.dtype(feats.descriptors.dtype).name}
        if rec.timestamp is not None:
            attrs["timestamp"] = float(rec.timestamp)
        if rec.pose is not None:
            attrs["pose"] = np.asarray(rec.pose, np.float64).reshape(12)
        grp.attrs.update(attrs)
        self.file.move(_TMP, f"keyframes/{int(rec.frame_id):08d}")
        self._maybe_flush()

    def add_gated(self, frame_id: int) -> None:
        """Records a frame the quality gate rejected."""
        ds = self.file["gated"]
        ds.resize((ds.shape[0] + 1,))
        ds[-1] = int(frame_id)
        self._maybe_flush()

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
        return str(self.file.attrs["encoder"])

    def _names(self) -> list[str]:
        """Complete keyframe groups in frame-id order (a half-written one from a killed run is never listed)."""
        return [n for n in self.file["keyframes"] if not n.startswith(".")]

    def __len__(self) -> int:
        return len(self._names())

    def gated(self) -> np.ndarray:
        """Frame ids the gate rejected, ``(n,)`` int64."""
        return self.file["gated"][()]

    def last_frame_id(self) -> int:
        """The largest frame id stored (keyframe or gated), -1 when empty."""
        names = self._names()
        last_kf = int(names[-1]) if names else -1  # groups are listed in name order: zero-padded ids
        gated = self.gated()
        return max(last_kf, int(gated.max()) if len(gated) else -1)

    def __iter__(self) -> Iterator[KeyframeRecord]:
        """Keyframes in frame-id order."""
        for name in self._names():
            yield self._read(self.file["keyframes"][name])

    @staticmethod
    def _features(grp: h5py.Group) -> Features:
        desc = grp["descriptors"][()].astype(grp.attrs["descriptor_dtype"], copy=False)
        return Features(grp["keypoints"][()], desc, grp["scales"][()])

    def features(self, frame_id: int) -> Features:
        """One keyframe's local features (descriptors in the extractor's dtype).

        Raises:
            KeyError: no complete keyframe with that id.
        """
        return self._features(self.file["keyframes"][f"{int(frame_id):08d}"])

    def search_entries(self) -> Iterator[tuple[int, np.ndarray, float | None]]:
        """``(frame_id, code, timestamp)`` per keyframe in frame-id order, without reading features."""
        for name in self._names():
            grp = self.file["keyframes"][name]
            ts = grp.attrs.get("timestamp")
            yield int(grp.attrs["frame_id"]), grp["code"][()], None if ts is None else float(ts)

    def _read(self, grp: h5py.Group) -> KeyframeRecord:
        a = grp.attrs
        return KeyframeRecord(frame_id=int(a["frame_id"]), code=grp["code"][()], features=self._features(grp),
                              timestamp=float(a["timestamp"]) if "timestamp" in a else None,
                              pose=np.asarray(a["pose"]).reshape(3, 4) if "pose" in a else None,
                              source=str(a["source"]), edge_ratio=float(a["edge_ratio"]),
                              candidates=grp["candidates"][()], loop=int(a["loop"]))

    def results(self) -> Iterator[tuple[int, np.ndarray, int]]:
        """``(frame_id, candidates (k, 4), loop)`` per keyframe in frame-id order, without reading features."""
        for name in self._names():
            grp = self.file["keyframes"][name]
            yield int(grp.attrs["frame_id"]), grp["candidates"][()], int(grp.attrs["loop"])

    def poses(self) -> np.ndarray:
        """``(n, 3, 4)`` camera-to-world pose per keyframe in frame-id order, NaN where none was given."""
        grps = [self.file["keyframes"][n] for n in self._names()]
        return np.stack([np.asarray(g.attrs["pose"], np.float64).reshape(3, 4) if "pose" in g.attrs
                         else np.full((3, 4), np.nan) for g in grps]) if grps else np.zeros((0, 3, 4))

    def codes(self) -> tuple[np.ndarray, np.ndarray]:
        """All codes, ``(n, 4096)`` float32, with their frame ids ``(n,)``."""
        grps = [self.file["keyframes"][n] for n in self._names()]
        if not grps:
            return np.zeros((0, 0), np.float32), np.zeros(0, np.int64)
        return np.stack([g["code"][()] for g in grps]), np.array([g.attrs["frame_id"] for g in grps], np.int64)

    def close(self) -> None:
        if self.file.id.valid:
            self.file.flush()
            self.file.close()

    def __enter__(self) -> "KeyframeDatabase":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
