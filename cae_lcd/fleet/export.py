"""Corrected trajectories out of the fleet server, in the formats SLAM tools read (``evo``, the KITTI devkit).

- TUM: one line a pose, ``timestamp tx ty tz qx qy qz qw`` (camera-to-global, Hamilton quaternion, ``qw >= 0``).
- KITTI: one line a pose, the 12 numbers of the ``3x4`` camera-to-global matrix row-major, no timestamp (a
  KITTI file lines up with another only frame by frame: compare it with the ground truth of the same frames).

Poses are the server's corrected ones in the global frame (the anchor's map: ``cae_lcd.fleet.service``), rigid (the scale of each
keyframe's similarity is not part of a trajectory file). ``trajectory_rows`` joins the server's poses with the
keyframes' timestamps; ``write_trajectory`` writes either format; ``export_robot`` does both for one robot of a
running ``FleetService``; ``GET /robots/{name}/trajectory?format=tum|kitti`` (``cae_lcd.fleet.map_page``) serves them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.files import write_text_atomic
from retrieval.edges import rotation_to_quaternion

__all__ = ["FORMATS", "format_trajectory", "write_trajectory", "trajectory_rows", "corrected_trajectory",
           "export_robot"]

FORMATS = ("tum", "kitti")  #: trajectory file formats, also the file suffixes ``export_robot`` writes


def format_trajectory(times: np.ndarray, poses: np.ndarray, fmt: str) -> str:
    """``(N,)`` timestamps and ``(N, 3|4, 4)`` camera-to-global poses -> the text of a trajectory file.

    Raises:
        ConfigError: an unknown format, mismatched lengths or non-finite poses.
    """
    if fmt not in FORMATS:
        raise ConfigError(f"unknown trajectory format {fmt!r}; expected one of {', '.join(FORMATS)}")
    poses, times = np.asarray(poses, np.float64), np.asarray(times, np.float64).reshape(-1)
    if poses.ndim != 3 or poses.shape[1:] not in ((3, 4), (4, 4)) or len(times) != len(poses) \
            or not (np.isfinite(poses).all() and np.isfinite(times).all()):
        raise ConfigError(f"a trajectory needs one finite 3x4 or 4x4 pose per timestamp; got poses of shape "
                          f"{poses.shape} and {len(times)} timestamps")
    poses = poses[:, :3]
    lines = []
    for stamp, P in zip(times, poses):
        if fmt == "kitti":
            lines.append(" ".join(f"{v:.9e}" for v in P.reshape(12)))
        else:
            lines.append(f"{stamp:.9f} " + " ".join(f"{v:.9f}" for v in (*P[:, 3], *rotation_to_quaternion(P[:, :3]))))
    return "".join(line + "\n" for line in lines)


def write_trajectory(path: str | Path, times: np.ndarray, poses: np.ndarray, fmt: str) -> Path:
    """Writes ``format_trajectory(times, poses, fmt)`` to ``path`` (temporary file, then renamed); returns ``path``."""
    write_text_atomic(path, format_trajectory(times, poses, fmt))
    return Path(path)


def trajectory_rows(poses: dict[int, np.ndarray], stamps: dict[int, float]) -> tuple[np.ndarray, np.ndarray,
                                                                                     np.ndarray]:
    """keyframe -> ``(4, 4)`` corrected pose (``FleetClient.poses``) and keyframe -> timestamp ->
    ``(keyframes (N,), times (N,), poses (N, 4, 4))`` in keyframe order; keyframes without a timestamp are left out."""
    ids = np.array(sorted(k for k in poses if k in stamps), np.int64)
    return (ids, np.array([stamps[int(k)] for k in ids], np.float64),
            np.array([poses[int(k)] for k in ids], np.float64).reshape(-1, 4, 4))


def corrected_trajectory(service: Any, robot: str, wait: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """A ``FleetService`` robot's corrected trajectory: ``(times (N,), poses (N, 4, 4))`` in keyframe order (empty
    when the robot is not merged into the global frame yet)."""
    stamps = {k.keyframe: k.timestamp for k in service.store.keyframes(robot)}
    corrected = {p["keyframe"]: np.array(p["pose"]) for p in service.poses(robot, wait)}
    _, times, poses = trajectory_rows(corrected, stamps)
    return times, poses


def export_robot(service: Any, robot: str, out_dir: str | Path, wait: bool = True) -> dict[str, Path]:
    """Writes ``OUT/ROBOT.tum`` and ``OUT/ROBOT.kitti`` from a ``FleetService``'s corrected poses; returns
    format -> path. A robot not merged into the global frame yet gets empty files."""
    times, poses = corrected_trajectory(service, robot, wait)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return {fmt: write_trajectory(out / f"{robot}.{fmt}", times, poses, fmt) for fmt in FORMATS}
