"""A video file (``.mp4``, ``.avi``, ...) read with OpenCV, one frame of every ``stride``, decoded lazily: frame
``i`` is video frame ``i * stride`` at ``i * stride / fps`` seconds. No intrinsics (the fundamental matrix is used).

A damaged packet is one unreadable frame, never a shift of the later ones: each decoded frame's own presentation
time says which video frame it is (a damaged stretch of a Matroska file: the frames after it keep their numbers, the
lost ones are reported unreadable), and an MJPG AVI is read through its index by OpenCV's own MJPEG reader
(FFmpeg's AVI reader numbers the packets it finds, so a zeroed stretch moved every later frame back).
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import cv2
import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import check_image, fingerprint

from .base import Sequence

__all__ = ["MAX_STRIDE", "VIDEO_EXTENSIONS", "VideoFrames", "is_video", "open_video"]

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")  #: file name endings read as a video
_SEEK_AHEAD = 64  #: a frame at most this many frames ahead is reached by grabbing rather than seeking
MAX_STRIDE = 2**31 - 1  #: OpenCV's frame positions are 32-bit
#: containers FFmpeg reads packet after packet without an index, where a frame's number is checked against its
#: presentation time (a damaged stretch skipped by the demuxer otherwise shifts every later frame)
PTS_CHECKED = (".mkv", ".webm")
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
        self._api = _backend(path)
        self._cap = cv2.VideoCapture(str(path), self._api)
        if not self._cap.isOpened():
            raise ConfigError(f"cannot open video {path}: not a video OpenCV can decode")
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:
            raise ConfigError(f"video {path} holds no frame (or does not say how many)")
        self.fps = float(self._cap.get(cv2.CAP_PROP_FPS))
        self._len = (count + stride - 1) // stride
        self._next = 0  # the video frame the next read() returns
        #: (first frame lost, frame decoded past them, its image) after a damaged stretch, else None
        self._ahead: tuple[int, int, np.ndarray] | None = None
        self._pts_offset: int | None = None  # presentation time of frame 0, in frames (``_position``)

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
            ok, image = self._decode(target)
        if not ok or image is None:
            return ImageError(f"cannot decode frame {target} of {self.path}"), ""
        image = _grey_if_grey(image)
        try:
            return check_image(image, self.name(i)), fingerprint(image.tobytes())
        except ImageError as err:
            return err, fingerprint(image.tobytes())

    def _decode(self, target: int) -> tuple[bool, np.ndarray | None]:
        """Video frame ``target`` (under the lock): grabbed forward, or sought; ``(False, None)`` when it cannot be
        decoded or was lost (the frame decoded in its place is another one: kept for its own number)."""
        if self._ahead is not None:
            lost_from, at, image = self._ahead
            if lost_from <= target < at:  # lost in the damaged stretch
                return False, None
            if target == at:
                self._ahead, self._next = None, target + 1
                return True, image
            self._ahead = None
        seek = not 0 <= target - self._next <= _SEEK_AHEAD
        if seek:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, target)
            self._next = target
        while self._next < target and self._cap.grab():
            self._next += 1
        ok, image = self._cap.read()
        if not ok and seek:  # a container that cannot seek here (a one-frame video): from the start instead
            ok, image = self._read_from_start(target)
        at = self._position(target) if ok else None
        self._next = target + 1 if ok else -_SEEK_AHEAD - 1  # after a failure: seek next time
        if at is not None and at > target:  # frames lost in a damaged stretch: this one is frame ``at``
            self._ahead, self._next = (target, at, image), at + 1
            return False, None
        return ok, image

    def _position(self, target: int) -> int | None:
        """The video frame just decoded, from its own presentation time, in a container read without an index
        (``PTS_CHECKED``; None elsewhere: MP4 and MOV are read through their sample table). The first frame decoded
        sets the offset of the presentation times."""
        if self.path.suffix.lower() not in PTS_CHECKED or self.fps <= 0:
            return None
        msec = self._cap.get(cv2.CAP_PROP_POS_MSEC)
        if not np.isfinite(msec) or msec < 0:
            return None
        raw = int(round(msec * self.fps / 1000.0))
        if self._pts_offset is None:
            self._pts_offset = raw - target
        return raw - self._pts_offset

    def _read_from_start(self, target: int) -> tuple[bool, np.ndarray | None]:
        """Video frame ``target`` read from a capture opened again, grabbing every frame before it."""
        self._cap.release()
        self._cap = cv2.VideoCapture(str(self.path), self._api)
        for _ in range(target):
            if not self._cap.grab():
                return False, None
        return self._cap.read()


def _has_avi_index(path: Path) -> bool:
    """Whether an AVI file has its index (an ``idx1`` chunk at the top level of its RIFF), found by skipping from
    chunk header to chunk header (a few reads, whatever the file's size)."""
    try:
        with path.open("rb") as fh:
            if fh.read(12)[8:12] != b"AVI ":
                return False
            while len(head := fh.read(8)) == 8:
                if head[:4] == b"idx1":
                    return True
                fh.seek(int.from_bytes(head[4:], "little") + (head[4] & 1), 1)
    except OSError:
        return False
    return False


def _backend(path: Path) -> int:
    """OpenCV's own MJPEG reader for an MJPG AVI with its index (it reads frames through the index), else OpenCV's
    first choice (FFmpeg)."""
    if path.suffix.lower() == ".avi" and _has_avi_index(path):
        probe = cv2.VideoCapture(str(path))
        fourcc = int(probe.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little") if probe.isOpened() else b""
        probe.release()
        if fourcc.upper() == b"MJPG" and cv2.VideoCapture(str(path), cv2.CAP_OPENCV_MJPEG).isOpened():
            return cv2.CAP_OPENCV_MJPEG
    return cv2.CAP_ANY  # FFmpeg (naming it warns on stderr when a file is no video)


def open_video(root: Path, stride: int = 1) -> Sequence:
    """Opens a video file as a sequence of every ``stride``-th frame.

    Raises:
        ConfigError: not a video OpenCV can open, or one without frames.
    """
    frames = VideoFrames(root, stride)
    return Sequence(root, [], timestamps=frames.times(), kind="video", stream=frames)
