"""A video file (``.mp4``, ``.avi``, ...) read with OpenCV, one frame of every ``stride``, decoded lazily: frame
``i`` is video frame ``i * stride`` at ``i * stride / fps`` seconds. No intrinsics (the fundamental matrix is used).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import cv2
import numpy as np

from core.conf import ConfigError
from core.errors import ImageError
from core.images import check_image, fingerprint

from .base import Sequence

__all__ = ["VIDEO_EXTENSIONS", "VideoFrames", "is_video", "open_video"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")  #: file name endings read as a video
_SEEK_AHEAD = 64  #: a frame at most this many frames ahead is reached by grabbing rather than seeking
#: FFmpeg's own log (through OpenCV) to fatal errors only, unless the environment sets it: a broken or cut video
#: printed one line per damaged packet to stderr ("moov atom not found", "overread 8") beside the project's one
#: warning per frame. Read when OpenCV first opens a video, so set here, before any capture.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "8")


def is_video(root: Path) -> bool:
    """A file with a video extension."""
    return root.is_file() and root.suffix.lower() in VIDEO_EXTENSIONS


def _grey_if_grey(image: np.ndarray) -> np.ndarray:
    """A 3-channel frame whose channels are equal (a grey video) as one channel, as the image files were."""
    if image.ndim == 3 and np.array_equal(image[..., 0], image[..., 1]) and np.array_equal(image[..., 0],
                                                                                           image[..., 2]):
        return np.ascontiguousarray(image[..., 0])
    return image


class VideoFrames:
    """Frames ``0, stride, 2 * stride, ...`` of a video, decoded on demand (sequential reads never seek)."""

    def __init__(self, path: Path, stride: int = 1) -> None:
        self.path, self.stride = path, stride
        self._lock = threading.Lock()
        self._cap = cv2.VideoCapture(str(path))
        if not self._cap.isOpened():
            raise ConfigError(f"cannot open video {path}: not a video OpenCV can decode")
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            raise ConfigError(f"video {path} holds no frame (or does not say how many)")
        self.fps = float(self._cap.get(cv2.CAP_PROP_FPS))
        self._len = (count + stride - 1) // stride
        self._next = 0  # the video frame the next read() returns

    def __len__(self) -> int:
        return self._len

    def name(self, i: int) -> str:
        return f"{self.path.name}:{i * self.stride:06d}"

    def source_id(self, i: int) -> str:
        """The video's own frame number of frame ``i`` (``i * stride``)."""
        return str(i * self.stride)

    def times(self) -> np.ndarray | None:
        """``(N,)`` seconds from the video's frame rate; None when it gives none."""
        return np.arange(self._len) * self.stride / self.fps if self.fps > 0 else None

    def read(self, i: int) -> tuple[np.ndarray | ImageError, str]:
        target = i * self.stride
        with self._lock:
            seek = not 0 <= target - self._next <= _SEEK_AHEAD
            if seek:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, target)
                self._next = target
            while self._next < target and self._cap.grab():
                self._next += 1
            ok, image = self._cap.read()
            if not ok and seek:  # a container that cannot seek here (a one-frame video): from the start instead
                ok, image = self._read_from_start(target)
            self._next = target + 1 if ok else -_SEEK_AHEAD - 1  # after a failure: seek next time
        if not ok or image is None:
            return ImageError(f"cannot decode frame {target} of {self.path}"), ""
        image = _grey_if_grey(image)
        try:
            return check_image(image, self.name(i)), fingerprint(image.tobytes())
        except ImageError as err:
            return err, fingerprint(image.tobytes())

    def _read_from_start(self, target: int) -> tuple[bool, np.ndarray | None]:
        """Video frame ``target`` read from a capture opened again, grabbing every frame before it."""
        self._cap.release()
        self._cap = cv2.VideoCapture(str(self.path))
        for _ in range(target):
            if not self._cap.grab():
                return False, None
        return self._cap.read()


def open_video(root: Path, stride: int = 1) -> Sequence:
    """Opens a video file as a sequence of every ``stride``-th frame.

    Raises:
        ConfigError: not a video OpenCV can open, or one without frames.
    """
    frames = VideoFrames(root, stride)
    return Sequence(root, [], timestamps=frames.times(), kind="video", stream=frames)
