"""A video file (``.mp4``, ``.avi``, ...) read with OpenCV, one frame of every ``stride``, decoded lazily: frame
``i`` is video frame ``i * stride`` at ``i * stride / fps`` seconds. No intrinsics (the fundamental matrix is used).

A damaged packet is one unreadable frame, never a shift of the later ones: each decoded frame's own presentation
time says which video frame it is (a damaged stretch of a Matroska file: the frames after it keep their numbers, the
lost ones are reported unreadable), and an MJPG AVI is read through its index by OpenCV's own MJPEG reader.
Any other AVI (FFV1, MPEG-4, ...) is read by FFmpeg, whose AVI reader numbers the packets it finds (a zeroed stretch
moved every later frame back): its index (``idx1``) says where each frame's chunk is, so a chunk whose header is
gone is a lost frame (``AviDamage``), FFmpeg's packet count is mapped back to the index's frame numbers, and the
frames coded against a lost one (up to the next key frame) are unreadable too.
"""

from __future__ import annotations

import io
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import check_image, fingerprint

from .base import Sequence

__all__ = ["MAX_STRIDE", "VIDEO_EXTENSIONS", "AviDamage", "avi_damage", "VideoFrames", "is_video", "open_video"]

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm")  #: file name endings read as a video
_SEEK_AHEAD = 64  #: a frame at most this many frames ahead is reached by grabbing rather than seeking
MAX_STRIDE = 2**31 - 1  #: OpenCV's frame positions are 32-bit
#: containers FFmpeg reads packet after packet without an index, where a frame's number is checked against its
#: presentation time (a damaged stretch skipped by the demuxer otherwise shifts every later frame)
PTS_CHECKED = (".mkv", ".webm")
_AVI_MAX_INDEX = 16 * 10_000_000  #: an ``idx1`` chunk larger than this (10M frames) is not read
_KEYFRAME = 0x10  #: AVIIF_KEYFRAME, the ``idx1`` flag of a key frame
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
        #: a damaged AVI read by FFmpeg: which frame each packet is (read forward only, ``_decode_counted``)
        self._damage = avi_damage(path) if self._api != cv2.CAP_OPENCV_MJPEG else None
        if self._damage is not None:
            log.warning("%s", self._damage.describe(path))

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
                return image is not None, image
            self._ahead = None
        if self._damage is not None:
            return self._decode_counted(target, self._damage)
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

    def _decode_counted(self, target: int, damage: "AviDamage") -> tuple[bool, np.ndarray | None]:
        """Video frame ``target`` of a damaged AVI: grabbed forward from where the capture is (opened again to go
        back: FFmpeg's seek lands by the index, then counts packets again), each packet's frame number from its
        presentation time (FFmpeg's packet count) through ``damage``; a frame lost or coded against a lost one is
        ``(False, None)``, the one decoded past a lost ``target`` kept for its own number."""
        if target < self._next:
            self._reopen()
        at = self._next - 1
        while at < target:
            frame = damage.frame(self._packet()) if self._cap.grab() else None
            if frame is None:
                self._next = MAX_STRIDE  # opened again next time
                return False, None
            at = frame
        self._next = at + 1
        usable = at not in damage.unusable
        image = self._cap.retrieve()[1] if usable else None
        if at > target:
            self._ahead = (target, at, image)
            return False, None
        return usable and image is not None, image

    def _packet(self) -> int:
        """The number of the packet just grabbed, from its presentation time (an AVI's count its packets from 0)."""
        msec = self._cap.get(cv2.CAP_PROP_POS_MSEC)
        return int(round(msec * self.fps / 1000.0)) if np.isfinite(msec) and self.fps > 0 else -1

    def _reopen(self) -> None:
        """The capture opened again, at the video's first frame."""
        self._cap.release()
        self._cap = cv2.VideoCapture(str(self.path), self._api)
        self._next = 0

    def _read_from_start(self, target: int) -> tuple[bool, np.ndarray | None]:
        """Video frame ``target`` read from a capture opened again, grabbing every frame before it."""
        self._reopen()
        for _ in range(target):
            if not self._cap.grab():
                return False, None
        return self._cap.read()


def _avi_chunks(path: Path) -> tuple[int | None, bytes | None]:
    """An AVI file's top-level RIFF chunks, skipped from header to header (a few reads, whatever the file's size):
    ``(file offset of the 'movi' list's type, the idx1 chunk's data)``, each None when absent (or not an AVI)."""
    movi, index = None, None
    try:
        with path.open("rb") as fh:
            if fh.read(12)[8:12] != b"AVI ":
                return None, None
            pos = 12
            while len(head := fh.read(12)) >= 8:
                size = int.from_bytes(head[4:8], "little")
                if head[:4] == b"LIST" and head[8:12] == b"movi" and movi is None:
                    movi = pos + 8
                elif head[:4] == b"idx1":
                    fh.seek(pos + 8)
                    index = fh.read(size) if size <= _AVI_MAX_INDEX else None
                    break
                pos += 8 + size + (size & 1)
                fh.seek(pos)
    except OSError:
        return None, None
    return movi, index


@dataclass(frozen=True)
class AviDamage:
    """A damaged AVI as FFmpeg reads it: the frames whose chunk it still finds, in order (its ``n``-th packet, by
    presentation time, is ``found[n]``: an AVI's times count packets), and the frames that cannot be used."""

    found: tuple[int, ...]  #: the video frames whose chunk header is intact, in the file's order
    lost: tuple[int, ...]  #: the frames whose chunk header is not where the index says
    unusable: frozenset[int]  #: ``lost`` and the frames coded against one of them (up to the next key frame)

    def frame(self, packet: int) -> int | None:
        """The video frame of FFmpeg's ``packet``-th packet; None out of range."""
        return self.found[packet] if 0 <= packet < len(self.found) else None

    def describe(self, path: Path) -> str:
        """One line for the log."""
        spans = _spans(sorted(self.unusable))
        return (f"video {path}: {len(self.lost)} frames' chunks are not where the file's index puts them (a damaged "
                f"stretch); frames {spans} are unreadable ({len(self.unusable)}), the others keep their numbers")


def _spans(ids: list[int]) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    out: list[list[int]] = []
    for i in ids:
        if out and i == out[-1][1] + 1:
            out[-1][1] = i
        else:
            out.append([i, i])
    return ", ".join(f"{a}-{b}" if b > a else str(a) for a, b in out)


def avi_damage(path: Path) -> AviDamage | None:
    """What the index of an AVI says of its first video stream's chunks: None for a file that is no AVI, has no
    index, or whose every frame's chunk header (id and size) is where the index puts it (a sound file: nothing to
    map); else ``AviDamage``. One 8-byte read a frame."""
    if path.suffix.lower() != ".avi":
        return None
    movi, index = _avi_chunks(path)
    if movi is None or not index:
        return None
    entries = [(index[k:k + 4], int.from_bytes(index[k + 4:k + 8], "little"), int.from_bytes(index[k + 8:k + 12],
                "little"), int.from_bytes(index[k + 12:k + 16], "little")) for k in range(0, len(index) - 15, 16)]
    video = [e for e in entries if e[0][2:4] in (b"dc", b"db")]
    video = [e for e in video if e[0][:2] == video[0][0][:2]] if video else []
    if not video:
        return None
    try:
        with path.open("rb") as fh:
            base = _index_base(fh, movi, video[0])
            if base is None:
                return None
            intact = []
            for chunk, _, offset, size in video:
                fh.seek(base + offset)
                head = fh.read(8)
                intact.append(head[:4] == chunk and int.from_bytes(head[4:8], "little") == size)
    except OSError:
        return None
    if all(intact):
        return None
    lost = [i for i, ok in enumerate(intact) if not ok]
    unusable, broken = set(lost), False
    for i, (_, flags, _, _) in enumerate(video):
        broken = not intact[i] or (broken and not flags & _KEYFRAME)
        if broken:
            unusable.add(i)
    return AviDamage(tuple(i for i, ok in enumerate(intact) if ok), tuple(lost), frozenset(unusable))


def _index_base(fh: "io.BufferedReader", movi: int, first: tuple[bytes, int, int, int]) -> int | None:
    """Where an ``idx1`` entry's offsets count from: the 'movi' list's type (the usual) or the file's start (some
    writers), whichever has the first entry's chunk there; None: neither (the index cannot be trusted)."""
    for base in (movi, 0):
        fh.seek(base + first[2])
        if fh.read(4) == first[0]:
            return base
    return None


def _has_avi_index(path: Path) -> bool:
    """Whether an AVI file has its index (an ``idx1`` chunk at the top level of its RIFF)."""
    return _avi_chunks(path)[1] is not None


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
