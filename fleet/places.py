"""The fleet's one place memory across robots: every robot's searched entries in a ``retrieval.places`` memory (the
detector's own kind, built by ``create_places``; its code index faiss, or Milvus with ``index.name: milvus``), keyed
by ``(robot, keyframe)``.

Cross-robot search has no recency exclusion (another robot's frame is never "recent"), and a query from outside
the memory's own sequence is not registered in its similarity table (``Places.undo`` right after the search), so
the memory holds each entry once, in its index. What stays in this process per keyframe is its key (two ints), and
its entry with an in-process index (faiss); none with Milvus.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from retrieval.descriptors import GlobalDescriptor
from retrieval.places import Places, create_places

__all__ = ["FleetPlaces"]

log = logging.getLogger(__name__)


class FleetPlaces:
    """Every robot's keyframe entries, searched across robots.

    Args:
        descriptor: the detectors' global descriptor (decides the kind of memory, as for a detector).
        whitening: the detectors' whitening (``LoopDetector.whitening``), or None.
        detector_conf: a resolved detector conf (its ``search`` section is replaced: nothing excluded).
        index_conf: the code index of the memory (``retrieval.index``: ``{"name": "flat"}``, ``{"name": "milvus",
            "uri": ...}``); None: the detector conf's.
    """

    def __init__(self, descriptor: GlobalDescriptor, whitening: Any, detector_conf: dict[str, Any],
                 index_conf: dict[str, Any] | None = None) -> None:
        conf = {**detector_conf, "search": {**detector_conf["search"], "exclude_recent": 0, "exclude_recent_s": None}}
        if index_conf is not None:
            conf["index"] = index_conf
        self.places: Places = create_places(descriptor, whitening, conf)
        self.keys: list[tuple[str, int]] = []  # place id -> (robot, keyframe)
        self._known: set[tuple[str, int]] = set()

    def __len__(self) -> int:
        return len(self.keys)

    def __contains__(self, key: object) -> bool:
        return key in self._known

    def add(self, robot: str, keyframe: int, entry: np.ndarray) -> None:
        """Inserts a keyframe's searched entry (``LoopDetector.places.entry`` of its code); a known key is skipped."""
        key = (robot, int(keyframe))
        if key in self._known:
            return
        self.places.insert(len(self.keys), entry, None)
        self.keys.append(key)
        self._known.add(key)

    def search(self, robot: str, entry: np.ndarray, k: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """The ``k`` most similar entries of the memory, the robot's own left out, grouped by robot.

        Returns:
            ``{other robot: (keyframes (m,) int64, scores (m,) float32)}``, best first.
        """
        query = len(self.keys)  # the id the next entry would take: registered by the search, then forgotten
        scores, ids = self.places.search(query, entry, None, max(int(k), 1))
        self.places.undo(query)
        out: dict[str, tuple[list[int], list[float]]] = {}
        for score, pid in zip(scores.tolist(), ids.tolist()):
            other, keyframe = self.keys[pid]
            if other != robot:
                found = out.setdefault(other, ([], []))
                found[0].append(keyframe)
                found[1].append(score)
        return {o: (np.asarray(kf, np.int64), np.asarray(s, np.float32)) for o, (kf, s) in out.items()}

    def close(self) -> None:
        """Closes the memory's index when it holds a connection (Milvus)."""
        index = getattr(getattr(self.places, "index", None), "index", None)
        if hasattr(index, "close"):
            index.close()
