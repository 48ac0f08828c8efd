"""A KITTI odometry sequence folder, or a plain folder of images in name order.

Every entry with an image extension is a frame, also one that cannot be read (a broken link, a folder named like an
image): it keeps its frame id and the detector skips and counts it, so ids never shift. Metadata files that cannot
be parsed are refused with the file and line named.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.images import image_entries

from .base import Sequence, read_numbers, rotation_in_pose

__all__ = ["open_folder", "read_kitti_calib", "read_kitti_poses", "read_times", "kitti_metadata_file", "CAMERAS"]

log = logging.getLogger(__name__)

CAMERAS = ("image_0", "image_2", "image_1", "image_3", "images")  #: camera folders, in the order looked for


def kitti_metadata_file(root: str | Path, what: str) -> Path | None:
    """Where a KITTI sequence keeps ``what`` ("poses", "times", "calib", "loops"); None when absent.

    Poses: ``poses.txt`` inside the sequence, else ``../../poses/<name>.txt`` (the KITTI odometry release layout).
    This is the one place that knows the layout.
    """
    root = Path(root)
    places = {"poses": [root / "poses.txt", root.parent.parent / "poses" / f"{root.name}.txt"],
              "times": [root / "times.txt"], "calib": [root / "calib.txt"], "loops": [root / "loops.txt"]}[what]
    return next((p for p in places if p.is_file()), None)


def read_kitti_calib(path: str | Path, camera: str = "image_0") -> np.ndarray:
    """``K (3, 3)`` of ``P0`` (``image_0``), ``P1``, ``P2`` (``image_2``) or ``P3`` from a KITTI ``calib.txt``.

    Raises:
        ConfigError: unreadable file, no line for the camera, or a matrix that is not finite with fx, fy > 0.
    """
    key = "P" + camera.split("_")[-1] + ":"
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"cannot read calibration {path}: {getattr(err, 'strerror', None) or err}") from None
    for n, line in enumerate(lines, 1):
        if line.startswith(key):
            try:
                P = np.array([float(v) for v in line.split()[1:13]]).reshape(3, 4)
            except ValueError:
                raise ConfigError(f"{path}, line {n}: '{key}' needs 12 numbers") from None
            K = P[:, :3].copy()
            if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
                raise ConfigError(f"{path}, line {n}: '{key}' is not a valid camera matrix (finite, fx and fy > 0)")
            return K
    raise ConfigError(f"{path} has no line '{key}' for camera {camera}")


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """KITTI poses file (12 finite numbers a line, 3x4 row-major) -> ``(N, 3, 4)``.

    Raises:
        ConfigError: unreadable file, a line without 12 numbers, a NaN/inf value or a 3x3 block that is not a
            rotation (file and line named).
    """
    return read_numbers(path, 12, "poses", row_check=rotation_in_pose).reshape(-1, 3, 4)


def read_times(path: str | Path) -> np.ndarray:
    """KITTI ``times.txt`` (one finite number of seconds a line) -> ``(N,)``.

    Raises:
        ConfigError: unreadable file, or a line that is not one finite number (file and line named).
    """
    return read_numbers(path, 1, "times").reshape(-1)


def _metadata(seq: Sequence, camera: str) -> Sequence:
    """Fills calibration, times and poses of a KITTI sequence; ones whose length does not fit are ignored."""
    root, n = seq.root, len(seq.frames)
    calib, times, poses = (kitti_metadata_file(root, w) for w in ("calib", "times", "poses"))
    if calib is not None:
        seq.K = read_kitti_calib(calib, camera)
    if times is not None:
        seq.timestamps = read_times(times)
    if poses is not None:
        seq.poses = read_kitti_poses(poses)
    seq.ground_truth = kitti_metadata_file(root, "loops")
    for name, path in (("timestamps", times), ("poses", poses)):
        value = getattr(seq, name)
        if value is not None and len(value) != n:
            log.warning("%s: %d %s for %d frames; ignoring them", path, len(value), name, n)
            setattr(seq, name, None)
    if seq.timestamps is not None and np.any(np.diff(seq.timestamps) < 0):
        log.warning("%s: timestamps go backwards; ignoring them", times)
        seq.timestamps = None
    return seq


def open_folder(root: Path, camera: str | None = None) -> Sequence:
    """Opens a KITTI sequence folder (``image_0/`` or ``image_2/``, ``calib.txt``, ``times.txt``, poses in
    ``poses.txt`` or ``../../poses/NN.txt``, ``loops.txt``) or a plain folder of images (and its ``loops.txt``).

    Args:
        root: the sequence folder.
        camera: ``"image_0"`` or ``"image_2"`` for KITTI; None picks the first present.

    Raises:
        ConfigError: missing folder, no images, or metadata that cannot be parsed.
    """
    cams = [camera] if camera else list(CAMERAS)
    cam = next((c for c in cams if (root / c).is_dir()), None)
    if camera and cam is None:
        raise ConfigError(f"{root} has no camera folder {camera}/")
    folder = root if cam is None else root / cam
    try:
        frames = image_entries(folder)
    except OSError as err:
        raise ConfigError(f"cannot list {folder}: {err.strerror or err}") from None
    if not frames:
        raise ConfigError(f"no images found in {folder}")
    if cam is None:  # a plain folder: only its own ``loops.txt`` (pairs of its frames) is read beside the images
        return Sequence(root, frames, ground_truth=kitti_metadata_file(root, "loops"))
    return _metadata(Sequence(root, frames, kind="kitti"), cam)
