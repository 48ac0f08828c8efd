"""EuRoC / ASL layout: ``mav0/cam0/data.csv`` (``timestamp [ns],NAME.png`` a line, images in ``mav0/cam0/data/``),
the camera from ``mav0/cam0/sensor.yaml`` (``intrinsics: [fu, fv, cu, cv]``, ``distortion_model``,
``distortion_coefficients``, ``T_BS``: ``verify.camera``) and, when present, the ground truth
``mav0/state_groundtruth_estimate0/data.csv`` (``timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z, ...``: the body in a
z-up world), from which each frame gets its camera's pose (the body's times ``T_BS``, in EuRoC's own world) and
``evaluate`` derives the loop ground truth. PATH may be the
folder holding ``mav0/`` or ``mav0/`` itself.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from cae_lcd.core.conf import ConfigError
from verify.camera import CameraModel, read_camera_file

from .base import Sequence, poses_at, read_numbers, read_stamped_names, unit_quaternion

__all__ = ["is_euroc", "open_euroc"]

log = logging.getLogger(__name__)

_NS = 1e-9  #: EuRoC timestamps are nanoseconds


def _mav(root: Path) -> Path:
    return root if root.name == "mav0" else root / "mav0"


def is_euroc(root: Path) -> bool:
    """A folder with ``mav0/cam0/data.csv`` (or ``mav0/`` itself)."""
    return root.is_dir() and (_mav(root) / "cam0" / "data.csv").is_file()


def _camera(path: Path) -> CameraModel | None:
    """The camera of a ``sensor.yaml`` (intrinsics, distortion, ``T_BS``: ``verify.camera``); None (with a warning)
    when absent or without valid ``intrinsics``."""
    if not path.is_file():
        return None
    try:
        return read_camera_file(path)
    except ConfigError as err:
        log.warning("%s; the fundamental matrix is used", err)
        return None


def _pose_row(values: list[float]) -> str | None:
    """A ground-truth line: at least 8 columns, ``q_w, q_x, q_y, q_z`` (columns 5-8) a unit quaternion."""
    if len(values) < 8:
        return f"expected at least 8 columns (timestamp, p_xyz, q_wxyz), got {len(values)}"
    return unit_quaternion(4)(values)


def open_euroc(root: Path) -> Sequence:
    """Opens a EuRoC / ASL sequence (``cam0``).

    Raises:
        ConfigError: ``data.csv`` or the ground truth cannot be parsed (a quaternion that is not a unit one
            included), a frame's path leaves the folder, or no frame is listed.
    """
    cam = _mav(root) / "cam0"
    times, names = read_stamped_names(cam / "data.csv", sep=",", scale=_NS)
    if not names:
        raise ConfigError(f"{cam / 'data.csv'} lists no frame")
    camera = _camera(cam / "sensor.yaml")
    seq = Sequence(root, [cam / "data" / n for n in names], timestamps=times, kind="euroc", camera=camera,
                   K=None if camera is None else camera.K)
    gt = _mav(root) / "state_groundtruth_estimate0" / "data.csv"
    if gt.is_file():
        rows = read_numbers(gt, None, "ground-truth poses", sep=",", row_check=_pose_row)
        if len(rows) and rows.shape[1] < 8:
            raise ConfigError(f"{gt}: expected at least 8 columns (timestamp, p_xyz, q_wxyz), got {rows.shape[1]}")
        track = np.column_stack([rows[:, 0] * _NS, rows[:, 1:4], rows[:, 5:8], rows[:, 4]]) if len(rows) \
            else np.zeros((0, 8))  # -> t, xyz, xyzw
        body = poses_at(times, track[track[:, 0].argsort()], gt, z_up=False)  # the body in EuRoC's z-up world
        seq.poses = body if body is None or camera is None or camera.T_body_camera is None else \
            body @ camera.T_body_camera  # T_WB T_BS: the camera's pose (a 3x4 times a 4x4)
        seq.poses_are_truth = seq.poses is not None
    return seq
