"""What every sequence reader gives: a ``Sequence`` (frames in order, and when known timestamps, poses, intrinsics
and ground truth), numeric text files read with the file and line named, and poses from a timestamped trajectory.

Frames live either as image files (``Sequence.frames``: KITTI, plain folders, TUM, EuRoC) or inside one file
(``Sequence.stream``: a bag, a video), read lazily one at a time by index. Either way ``read_frame(i)`` gives
``(image or the reason it cannot be read, fingerprint)``, so the detector never knows which.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Protocol

import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import decode_image, fingerprint, read_file
from verify.camera import CameraModel

__all__ = ["Sequence", "FrameStream", "read_numbers", "read_stamped_names", "read_file_frame", "poses_at",
           "unit_quaternion", "rotation_in_pose", "Z_UP_TO_KITTI"]

log = logging.getLogger(__name__)

#: rotates a z-up world (TUM, EuRoC: gravity along -z) into the KITTI convention (y down, x-z the ground plane),
#: so that ground truth is derived on the ground plane for every layout (``cae_lcd.evaluation.ground_truth``)
Z_UP_TO_KITTI = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class FrameStream(Protocol):
    """Frames stored inside one file (a bag, a video), read lazily by index."""

    def __len__(self) -> int: ...

    def name(self, i: int) -> str:
        """What the keyframe database records as frame ``i``'s source (stable across runs)."""
        ...

    def read(self, i: int) -> tuple[np.ndarray | ImageError, str]:
        """Frame ``i`` as ``(image (H, W[, 3]) or the reason it cannot be read, fingerprint of its bytes)``."""
        ...

    def source_id(self, i: int) -> str:
        """Frame ``i``'s id in the file as its own tools number it (a video frame number, a bag message index)."""
        ...


@dataclass
class Sequence:
    root: Path
    frames: list[Path]  #: image files in order (empty when the frames are inside one file: ``stream``)
    timestamps: np.ndarray | None = None  #: (N,) seconds
    poses: np.ndarray | None = None  #: (N, 3, 4) camera-to-world
    K: np.ndarray | None = field(default=None, repr=False)  #: (3, 3) intrinsics of the camera used
    ground_truth: Path | None = None  #: ``loops.txt`` beside the frames, when present
    kind: str = "folder"
    stream: FrameStream | None = field(default=None, repr=False)  #: frames inside one file (bag, video)
    poses_are_truth: bool = False  #: ``poses`` are ground truth: the loop ground truth is derived from them
    camera: CameraModel | None = field(default=None, repr=False)  #: the camera's own model when the layout gives
    #: one with its distortion (EuRoC ``sensor.yaml``, a bag's ``CameraInfo``); ``K`` is its ``K``

    def __len__(self) -> int:
        return len(self.stream) if self.stream is not None else len(self.frames)

    @property
    def name(self) -> str:
        """The sequence's name: its folder's, or the file's without its extension."""
        return self.root.name if self.root.is_dir() else self.root.stem

    def frame_name(self, i: int) -> str:
        """Frame ``i``'s source as the keyframe database records it (file name, or ``stream.name(i)``)."""
        return self.stream.name(i) if self.stream is not None else self.frames[i].name

    def source_id(self, i: int) -> str:
        """Frame ``i``'s id in its source, for the user to join results with their own data: the image file's
        path relative to the sequence (``image_0/000012.png``, ``rgb/1305031102.175304.png``), or the stream's
        (``FrameStream.source_id``: a video's frame number, a bag's message index on the topic)."""
        if self.stream is not None:
            return self.stream.source_id(i)
        path = self.frames[i]
        return path.relative_to(self.root).as_posix() if path.is_relative_to(self.root) else path.name

    def read_frame(self, i: int) -> tuple[np.ndarray | ImageError, str]:
        """Frame ``i``: ``(image or the reason it cannot be read, fingerprint or "")``."""
        return self.stream.read(i) if self.stream is not None else read_file_frame(self.frames[i])


def read_file_frame(path: Path) -> tuple[np.ndarray | ImageError, str]:
    """An image file as ``(image or the reason it cannot be read, fingerprint of the file or "")``."""
    try:
        data = read_file(path)
    except ImageError as err:
        return err, ""
    try:
        return decode_image(data, path), fingerprint(data)
    except ImageError as err:
        return err, fingerprint(data)


def read_numbers(path: str | Path, per_line: int | None = None, what: str = "numbers",
                 sep: str | None = None, row_check: RowCheck | None = None) -> np.ndarray:
    """A numeric text file -> ``(R, C)`` float64 (``(0, per_line or 0)`` when it holds none); ``#`` comments and
    blank lines skipped.

    Args:
        sep: the separator (None: whitespace; ``","`` for CSV).
        row_check: ``row_check(values)`` -> what is wrong with a line's values, or None (``unit_quaternion``).

    Raises:
        ConfigError: unreadable file, a non-numeric or non-finite value, a line of another length or refused by
            ``row_check`` (the message names the file and line).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read {what} file {path}: {getattr(err, 'strerror', None) or err}") from None
    rows = []
    for n, line in enumerate(text.splitlines(), 1):
        parts = [p for p in line.split("#")[0].split(sep) if p.strip()]
        if not parts:
            continue
        try:
            values = [float(v) for v in parts]
        except ValueError:
            raise ConfigError(f"{path}, line {n}: not a number in {line.strip()[:60]!r}") from None
        if per_line is not None and len(values) != per_line:
            raise ConfigError(f"{path}, line {n}: expected {per_line} numbers, got {len(values)}")
        if not np.isfinite(values).all():
            raise ConfigError(f"{path}, line {n}: NaN or infinite value in {what}")
        wrong = row_check(values) if row_check is not None else None
        if wrong:
            raise ConfigError(f"{path}, line {n}: {wrong}")
        rows.append(values)
    width = per_line if per_line is not None else (len(rows[0]) if rows else 0)
    if not rows:
        return np.zeros((0, width), np.float64)
    if any(len(r) != width for r in rows):
        raise ConfigError(f"{path}: lines of different lengths")
    return np.array(rows, np.float64).reshape(-1, width)


RowCheck = Callable[[list[float]], "str | None"]

#: how far from 1 a ground-truth quaternion's norm may be (files print 4-9 decimals); it is normalised
QUATERNION_NORM_TOLERANCE = 0.01
#: how far from the identity a KITTI pose's ``R R^T`` may be, entry by entry
ROTATION_TOLERANCE = 0.01


def unit_quaternion(start: int) -> RowCheck:
    """A ``row_check`` for ``read_numbers``: the 4 values from column ``start`` are a unit quaternion."""

    def check(values: list[float]) -> str | None:
        norm = float(np.linalg.norm(values[start:start + 4]))
        if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
            return f"the quaternion (columns {start + 1}-{start + 4}) has norm {norm:.4g}, not 1"
        return None

    return check


def rotation_in_pose(values: list[float]) -> str | None:
    """A ``row_check`` for a 3x4 row-major pose: its left 3x3 block is a rotation."""
    R = np.asarray(values[:12], np.float64).reshape(3, 4)[:, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        return "the pose's 3x3 block is not a rotation"
    return None


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(N, 4)`` as ``(x, y, z, w)`` -> rotation matrices ``(N, 3, 3)``."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1)], 1)


def poses_at(times: np.ndarray, track: np.ndarray, path: Path, z_up: bool = True) -> np.ndarray | None:
    """Camera-to-world poses ``(N, 3, 4)`` at ``times`` ``(N,)`` from a trajectory ``(M, 8)``: ``t, x, y, z, qx,
    qy, qz, qw`` sorted by time (TUM's order; callers reorder EuRoC's). Positions are interpolated, the rotation is
    the nearest sample's; frames outside the trajectory's time range take its first or last pose. With ``z_up`` the
    world is turned into the KITTI convention (``Z_UP_TO_KITTI``). None (with a warning) when no frame lies within
    the trajectory's time range.
    """
    t = track[:, 0]
    if len(t) == 0:
        log.warning("%s holds no pose; no ground truth", path)
        return None
    if not (np.any((times >= t[0]) & (times <= t[-1]))):
        log.warning("%s: no frame lies within the ground truth's time range; no poses", path)
        return None
    outside = int(np.sum((times < t[0]) | (times > t[-1])))
    if outside:
        log.warning("%s: %d frames lie outside the ground truth's time range; they take its end poses", path, outside)
    xyz = np.stack([np.interp(times, t, track[:, k]) for k in (1, 2, 3)], 1)
    nearest = np.clip(np.searchsorted(t, times), 0, len(t) - 1)
    prev = np.clip(nearest - 1, 0, len(t) - 1)
    nearest = np.where(np.abs(t[prev] - times) < np.abs(t[nearest] - times), prev, nearest)
    R = _quat_to_matrix(track[nearest, 4:8])
    poses = np.concatenate([R, xyz[:, :, None]], axis=2)
    return Z_UP_TO_KITTI @ poses if z_up else poses


def read_stamped_names(path: Path, sep: str | None = None, scale: float = 1.0) -> tuple[np.ndarray, list[str]]:
    """A ``timestamp name`` list (TUM's ``rgb.txt``; EuRoC's ``data.csv`` with ``sep=","``) -> times ``(N,)`` in
    seconds (the file's unit times ``scale``) and the names, in time order; ``#`` lines skipped.

    Raises:
        ConfigError: unreadable file, a line without a timestamp and a name, a name that leaves the folder
            (absolute, or through ``..``), or two frames at the same time.
    """
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read {path}: {getattr(err, 'strerror', None) or err}") from None
    rows: list[tuple[float, str]] = []
    for n, line in enumerate(text.splitlines(), 1):
        parts = [p.strip() for p in line.split(sep) if p.strip()] if not line.lstrip().startswith("#") else []
        if not parts:
            continue
        try:
            if len(parts) != 2 or not np.isfinite(float(parts[0])):
                raise ValueError
        except ValueError:
            raise ConfigError(f"{path}, line {n}: expected 'timestamp{sep or ' '}file name', got "
                              f"{line.strip()[:60]!r}") from None
        name = Path(parts[1])
        if name.is_absolute() or ".." in name.parts:
            raise ConfigError(f"{path}, line {n}: {parts[1]!r} leaves the sequence's folder (a name inside it, "
                              "relative, without '..', is expected)")
        rows.append((float(parts[0]) * scale, parts[1]))
    rows.sort(key=lambda r: r[0])
    times = np.array([r[0] for r in rows], np.float64)
    if np.any(np.diff(times) == 0):
        raise ConfigError(f"{path}: two frames with the same timestamp")
    return times, [r[1] for r in rows]
