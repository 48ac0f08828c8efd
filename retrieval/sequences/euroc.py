"""EuRoC / ASL layout: ``mav0/cam0/data.csv`` (``timestamp [ns],NAME.png`` a line, images in ``mav0/cam0/data/``),
intrinsics from ``mav0/cam0/sensor.yaml`` (``intrinsics: [fu, fv, cu, cv]``) and, when present, the ground truth
``mav0/state_groundtruth_estimate0/data.csv`` (``timestamp, p_x, p_y, p_z, q_w, q_x, q_y, q_z, ...``: the body in a
z-up world), from which each frame gets a pose and ``evaluate`` derives the loop ground truth. PATH may be the
folder holding ``mav0/`` or ``mav0/`` itself.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import yaml

from core.conf import ConfigError

from .base import Sequence, poses_at, read_numbers, read_stamped_names, unit_quaternion

__all__ = ["is_euroc", "open_euroc"]

log = logging.getLogger(__name__)

_NS = 1e-9  #: EuRoC timestamps are nanoseconds


def _mav(root: Path) -> Path:
    return root if root.name == "mav0" else root / "mav0"


def is_euroc(root: Path) -> bool:
    """A folder with ``mav0/cam0/data.csv`` (or ``mav0/`` itself)."""
    return root.is_dir() and (_mav(root) / "cam0" / "data.csv").is_file()


def _intrinsics(path: Path) -> np.ndarray | None:
    """``K (3, 3)`` from a ``sensor.yaml``; None (with a warning) when absent or without valid ``intrinsics``."""
    if not path.is_file():
        return None
    try:  # OpenCV writes a '%YAML:1.0' directive that PyYAML refuses
        text = "\n".join(ln for ln in path.read_text(encoding="utf-8").splitlines() if not ln.startswith("%"))
        fu, fv, cu, cv = (float(v) for v in yaml.safe_load(text)["intrinsics"])
    except (OSError, UnicodeDecodeError, yaml.YAMLError, KeyError, TypeError, ValueError):
        log.warning("%s: no 'intrinsics: [fu, fv, cu, cv]'; the fundamental matrix is used", path)
        return None
    if not (np.isfinite([fu, fv, cu, cv]).all() and fu > 0 and fv > 0):
        log.warning("%s: intrinsics are not finite with fu, fv > 0; the fundamental matrix is used", path)
        return None
    return np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])


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
    seq = Sequence(root, [cam / "data" / n for n in names], timestamps=times, K=_intrinsics(cam / "sensor.yaml"),
                   kind="euroc")
    gt = _mav(root) / "state_groundtruth_estimate0" / "data.csv"
    if gt.is_file():
        rows = read_numbers(gt, None, "ground-truth poses", sep=",", row_check=_pose_row)
        if len(rows) and rows.shape[1] < 8:
            raise ConfigError(f"{gt}: expected at least 8 columns (timestamp, p_xyz, q_wxyz), got {rows.shape[1]}")
        track = np.column_stack([rows[:, 0] * _NS, rows[:, 1:4], rows[:, 5:8], rows[:, 4]]) if len(rows) \
            else np.zeros((0, 8))  # -> t, xyz, xyzw
        seq.poses = poses_at(times, track[track[:, 0].argsort()], gt)
        seq.poses_are_truth = seq.poses is not None
    return seq
