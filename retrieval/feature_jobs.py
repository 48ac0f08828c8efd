"""Local-feature extraction off the caller's thread: one worker thread, each job done once by whichever thread gets
to it first (``runtime.feature_worker``); and the grey copy a keyframe keeps to extract its features again later.

A job is keyed by the frame id whose features it extracts. The worker runs queued jobs (urgent ones first); a
thread that needs a job's result (``take``) runs it itself when the worker has not started it yet (it never waits
behind the worker's queue), or waits for it when the worker is already running it. Each thread extracts with its
own extractor (OpenCV's feature objects are not shared between threads): a job is a function of the extractor.

    >>> jobs = FeatureJobs(lambda: create_extractor({"name": "sift"}))          # doctest: +SKIP
    >>> jobs.submit(12, lambda ex: ex.extract(gray), urgent=True)              # doctest: +SKIP
    >>> feats = jobs.take(12, my_extractor)   # Features, or None when no job was submitted for 12   # doctest: +SKIP

A grey copy (``grey_copy``) is the ``prepare``d grey image (at the extractor's resolution) as JPEG, or PNG when
lossless, after its scale to the original image (float64, 8 bytes): ``read_grey_copy`` gives back what
``extract_prepared`` takes.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections import OrderedDict, deque
from typing import Callable

import cv2
import numpy as np

from cae_lcd.core.errors import DatabaseError
from cae_lcd.core.threads import BesideCaller
from verify.features import FeatureExtractor, Features

__all__ = ["FeatureJobs", "grey_copy", "read_grey_copy"]

log = logging.getLogger(__name__)

Job = Callable[[FeatureExtractor], Features]  #: extracts one frame's features with the extractor given


class _Task:
    """One job's state: claimed by one thread (the one that runs it), then done with a result or an error."""

    def __init__(self, fn: Job) -> None:
        self.fn = fn
        self.done = threading.Event()
        self.result: Features | None = None
        self.error: BaseException | None = None
        self._claimed = False
        self._lock = threading.Lock()

    def claim(self) -> bool:
        with self._lock:
            if self._claimed:
                return False
            self._claimed = True
            return True

    def run(self, extractor: FeatureExtractor) -> None:
        try:
            self.result = self.fn(extractor)
        except BaseException as err:  # handed to the thread that takes the result
            self.error = err
        finally:
            self.done.set()


class FeatureJobs:
    """A worker thread extracting local features for frames ahead of need (see the module doc).

    Args:
        make_extractor: builds the worker's own extractor (configured as the caller's: the same features).
        keep: results done but not taken kept at most (oldest dropped first: a speculative job nobody needed).
    """

    def __init__(self, make_extractor: Callable[[], FeatureExtractor], keep: int = 64) -> None:
        self.keep = max(1, int(keep))
        self._extractor = make_extractor()
        self._tasks: OrderedDict[int, _Task] = OrderedDict()
        self._queue: deque[int] = deque()
        self._lock = threading.Lock()
        self._wake = threading.Condition(self._lock)
        self._closed = False
        self._steering = BesideCaller()  # the worker off the core of the thread that submits
        self._thread = threading.Thread(target=self._work, name="features", daemon=True)
        self._thread.start()

    def __contains__(self, frame_id: int) -> bool:
        with self._lock:
            return int(frame_id) in self._tasks

    def submit(self, frame_id: int, fn: Job, urgent: bool = False) -> None:
        """Queues ``fn`` for ``frame_id`` (nothing when a job for it is already there); ``urgent``: before the rest."""
        with self._lock:
            if self._closed or int(frame_id) in self._tasks:
                return
            self._tasks[int(frame_id)] = _Task(fn)
            (self._queue.appendleft if urgent else self._queue.append)(int(frame_id))
            self._trim()
            self._steering.steer()
            self._wake.notify()

    def take(self, frame_id: int, extractor: FeatureExtractor) -> Features | None:
        """The result of ``frame_id``'s job, which leaves the queue: run here with ``extractor`` when the worker has not
        started it, else waited for; None when there is no job for ``frame_id``. A job's error is raised here."""
        with self._lock:
            task = self._tasks.pop(int(frame_id), None)
        if task is None:
            return None
        if task.claim():
            task.run(extractor)
        task.done.wait()
        if task.error is not None:
            raise task.error
        return task.result

    def drop(self, frame_id: int) -> None:
        """Forgets ``frame_id``'s job (queued, running or done): its result is never taken."""
        with self._lock:
            self._tasks.pop(int(frame_id), None)

    def _trim(self) -> None:
        """Drops the oldest finished results past ``keep`` (under the lock)."""
        done = [fid for fid, task in self._tasks.items() if task.done.is_set()]
        for fid in done[: max(0, len(done) - self.keep)]:
            del self._tasks[fid]

    def _work(self) -> None:
        self._steering.attach()
        while True:
            with self._lock:
                while not self._queue and not self._closed:
                    self._wake.wait()
                if self._closed:
                    return
                task = self._tasks.get(self._queue.popleft())
            if task is not None and task.claim():
                task.run(self._extractor)

    def close(self) -> None:
        """Stops the worker once its current job is done; queued jobs are dropped (``take`` still runs them)."""
        with self._lock:
            self._closed = True
            self._queue.clear()
            self._wake.notify_all()
        self._thread.join()


def grey_copy(small: np.ndarray, scale: float, quality: int | None = None) -> bytes:
    """A prepared grey uint8 ``(h, w)`` image and its scale as stored: JPEG of ``quality`` (1-100), None: lossless
    PNG (then ``read_grey_copy`` gives ``small`` back exactly), deflated run by run (zlib's RLE strategy: on camera
    frames smaller and faster than its default, KITTI 90 at 384 px 28.8 -> 26.1 kB, 0.96 -> 0.74 ms)."""
    lossless = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE]
    ext, params = (".png", lossless) if quality is None else (".jpg", [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    ok, data = cv2.imencode(ext, small, params)
    if not ok:  # pragma: no cover - OpenCV encodes any 2-D uint8 image
        raise ValueError(f"could not encode a {small.shape} grey image as {ext}")
    return struct.pack("<d", float(scale)) + data.tobytes()


def read_grey_copy(copy: bytes) -> tuple[np.ndarray, float]:
    """``(image (h, w) uint8, scale)`` of a ``grey_copy``.

    Raises:
        DatabaseError: not a grey copy (damaged).
    """
    small = cv2.imdecode(np.frombuffer(copy, np.uint8, offset=8), cv2.IMREAD_GRAYSCALE) if len(copy) > 8 else None
    if small is None:
        raise DatabaseError(f"a keyframe's stored grey image cannot be decoded ({len(copy)} bytes); the store is damaged")
    return small, struct.unpack("<d", copy[:8])[0]
