"""Sequence readers: a KITTI odometry sequence folder, or a plain folder of images in name order.

A ``Sequence`` gives frame paths, and when known timestamps ``(N,)``, poses ``(N, 3, 4)`` camera-to-world,
intrinsics ``K (3, 3)`` and ground-truth loop pairs ``(P, 2)``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cae.conf import ConfigError
from cae.preprocess import IMAGE_EXTENSIONS

__all__ = ["Sequence", "open_sequence", "read_kitti_calib", "read_kitti_poses", "read_loop_pairs"]

log = logging.getLogger(__name__)


@dataclass
class Sequence:
    root: Path
    frames: list[Path]
    timestamps: np.ndarray | None = None  #: (N,) seconds
    poses: np.ndarray | None = None  #: (N, 3, 4) camera-to-world
    K: np.ndarray | None = field(default=None, repr=False)  #: (3, 3) intrinsics of the camera used
    loops: np.ndarray | None = field(default=None, repr=False)  #: (P, 2) ground-truth pairs (later, earlier)
    kind: str = "folder"

    def __len__(self) -> int:
        return len(self.frames)


def read_kitti_calib(path: str | Path, camera: str = "image_0") -> np.ndarray:
    """``K (3, 3)`` of ``P0`` (``image_0``), ``P1``, ``P2`` (``image_2``) or ``P3`` from a KITTI ``calib.txt``."""
    key = "P" + camera.split("_")[-1] + ":"
    for line in Path(path).read_text().splitlines():
        if line.startswith(key):
            P = np.array([float(v) for v in line.split()[1:13]]).reshape(3, 4)
            return P[:, :3].copy()
    raise ConfigError(f"{path} has no line '{key}' for camera {camera}")


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """KITTI poses file (12 floats a line, 3x4 row-major) -> ``(N, 3, 4)``."""
    data = np.loadtxt(path, ndmin=2)
    if data.shape[1] != 12:
        raise ConfigError(f"{path}: expected 12 numbers per line (3x4 pose), got {data.shape[1]}")
    return data.reshape(-1, 3, 4)


def read_loop_pairs(path: str | Path) -> np.ndarray:
    """Loop pairs file (``i j`` per line, ``#`` comments) -> ``(P, 2)`` int64 rows (later, earlier), unique, sorted."""
    rows = [line.split()[:2] for line in Path(path).read_text().splitlines()
            if line.strip() and not line.lstrip().startswith("#")]
    pairs = np.array(rows, dtype=np.int64).reshape(-1, 2)
    return np.unique(np.stack([pairs.max(1), pairs.min(1)], axis=1), axis=0) if len(pairs) else pairs


def _images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())


def open_sequence(path: str | Path, camera: str | None = None) -> Sequence:
    """Opens a KITTI sequence folder (``image_0/`` or ``image_2/``, ``calib.txt``, ``times.txt``, poses in
    ``../../poses/NN.txt`` or ``poses.txt``, ``loops.txt``) or a plain folder of images.

    Args:
        path: the sequence folder.
        camera: ``"image_0"`` or ``"image_2"`` for KITTI; None picks the first present.

    Raises:
        ConfigError: missing folder, no images, or metadata that does not fit the frames.
    """
    root = Path(path)
    if not root.is_dir():
        raise ConfigError(f"sequence folder not found: {root}")
    cams = [camera] if camera else ["image_0", "image_2", "image_1", "image_3"]
    cam = next((c for c in cams if (root / c).is_dir()), None)
    if camera and cam is None:
        raise ConfigError(f"{root} has no camera folder {camera}/")
    if cam is None:
        frames = _images_in(root)
        if not frames:
            raise ConfigError(f"no images found in {root}")
        return Sequence(root, frames)
    frames = _images_in(root / cam)
    if not frames:
        raise ConfigError(f"no images found in {root / cam}")
    seq = Sequence(root, frames, kind="kitti")
    if (root / "calib.txt").is_file():
        seq.K = read_kitti_calib(root / "calib.txt", cam)
    if (root / "times.txt").is_file():
        seq.timestamps = np.loadtxt(root / "times.txt", ndmin=1)
    for pose_file in (root / "poses.txt", root.parent.parent / "poses" / f"{root.name}.txt"):
        if pose_file.is_file():
            seq.poses = read_kitti_poses(pose_file)
            break
    if (root / "loops.txt").is_file():
        seq.loops = read_loop_pairs(root / "loops.txt")
    for name in ("timestamps", "poses"):
        value = getattr(seq, name)
        if value is not None and len(value) != len(frames):
            log.warning("%s: %d %s for %d frames; ignoring them", root, len(value), name, len(frames))
            setattr(seq, name, None)
    return seq
