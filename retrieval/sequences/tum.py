"""TUM RGB-D layout: ``rgb.txt`` (``timestamp rgb/NAME.png`` a line), ``groundtruth.txt`` (``timestamp tx ty tz qx
qy qz qw``, the camera in the recording's world: z up for TUM's own, y down for one ``evo`` wrote from KITTI poses)
when present. The ground truth gives each frame a pose (interpolated at its timestamp, kept in the file's world),
from which ``evaluate`` derives the loop ground truth (the gravity axis found, or ``--world``); TUM ships no
intrinsics file (the fundamental matrix is used, unless ``--intrinsics`` or ``--camera-info`` gives the camera).
"""

from __future__ import annotations

from pathlib import Path

from cae_lcd.core.conf import ConfigError

from .base import Sequence, poses_at, read_numbers, read_stamped_names, unit_quaternion

__all__ = ["is_tum", "open_tum"]


def is_tum(root: Path) -> bool:
    """A folder with ``rgb.txt``."""
    return root.is_dir() and (root / "rgb.txt").is_file()


def open_tum(root: Path) -> Sequence:
    """Opens a TUM RGB-D sequence folder.

    Raises:
        ConfigError: ``rgb.txt`` or ``groundtruth.txt`` cannot be parsed (a quaternion that is not a unit one
            included), a frame's path leaves the folder, or no frame is listed.
    """
    times, names = read_stamped_names(root / "rgb.txt")
    if not names:
        raise ConfigError(f"{root / 'rgb.txt'} lists no frame")
    seq = Sequence(root, [root / n for n in names], timestamps=times, kind="tum")
    gt = root / "groundtruth.txt"
    if gt.is_file():
        track = read_numbers(gt, 8, "ground-truth poses", row_check=unit_quaternion(4))
        seq.poses = poses_at(times, track[track[:, 0].argsort()], gt, z_up=False)  # in the file's own world
        seq.poses_are_truth = seq.poses is not None
    return seq
