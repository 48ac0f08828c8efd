"""Fixtures of the fleet tests: real KITTI ground-truth poses and 3D points built from them, a known similarity."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cae_lcd.fleet.recognition import FIXED_POLICY

#: 3D points in the camera frame (KITTI: x right, y down, z forward), metres: road edges, facades, a far point and
#: the camera centre. Placed at every real pose they make a real-shaped scene along the real trajectory.
CAMERA_OFFSETS = np.array([[-6.0, -3.0, 12.0], [6.0, -3.0, 12.0], [-4.0, 1.6, 8.0], [4.0, 1.6, 8.0],
                           [0.0, -8.0, 30.0], [0.0, 0.0, 0.0]])


#: the recognition conf of the tests about something other than calibration: their robots stream 2-60 keyframes,
#: within a detector's online warm-up (2 x search.exclude_recent keyframes, in which nothing is accepted), so they
#: run the fixed policy (policy.min_inliers, cross.min_inliers) as the fleet did before it calibrated online
FIXED = FIXED_POLICY


@pytest.fixture(scope="session")
def known_sim3():
    """The similarity robot B's frame differs by in these tests: s = 2.5, a 75 deg rotation, a translation."""
    from cae_lcd.fleet.sim3 import Sim3

    return Sim3(2.5, cv2.Rodrigues(np.array([0.3, -1.2, 0.5]))[0], np.array([10.0, -4.0, 7.0]))


def _landmarks(poses: np.ndarray) -> np.ndarray:
    """``(N, 3, 4)`` camera-to-world poses -> ``(6 N, 3)`` world points at ``CAMERA_OFFSETS`` of every pose."""
    return np.concatenate([CAMERA_OFFSETS @ p[:, :3].T + p[:, 3] for p in poses])


def _with_outliers(dst: np.ndarray, fraction: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``dst`` with ``fraction`` of its rows replaced by other rows (wrong matches to real structure).

    Returns:
        ``(points (n, 3), outlier mask (n,))``.
    """
    out = dst.copy()
    idx = rng.choice(len(dst), int(round(fraction * len(dst))), replace=False)
    out[idx] = dst[np.roll(idx, 1)]
    mask = np.zeros(len(dst), bool)
    mask[idx] = np.linalg.norm(out[idx] - dst[idx], axis=1) > 0
    return out, mask


@pytest.fixture(scope="session")
def kitti_poses(kitti_sequences):
    """``kitti_poses(seq)`` -> ``(N, 3, 4)`` ground-truth camera-to-world poses of ``../shared`` KITTI ``seq``."""
    from retrieval.sequences import read_kitti_poses

    def get(seq: str) -> np.ndarray:
        return read_kitti_poses(kitti_sequences.parent / "poses" / f"{seq}.txt")

    return get


@pytest.fixture(scope="session")
def kitti_landmarks(kitti_poses) -> np.ndarray:
    """``(600, 3)`` points along KITTI 00 (``landmarks`` of every second pose), metres."""
    return _landmarks(kitti_poses("00")[::2])


@pytest.fixture(scope="session")
def landmarks():
    """``landmarks(poses (N, 3, 4))`` -> ``(6 N, 3)`` points at ``CAMERA_OFFSETS`` of every pose."""
    return _landmarks


@pytest.fixture(scope="session")
def with_outliers():
    """``with_outliers(dst, fraction, rng)`` -> ``(points, outlier mask)``: rows replaced by other rows."""
    return _with_outliers


@pytest.fixture(scope="session")
def cae_descriptor():
    """The CAE descriptor with the shipped weights, loaded once for every server of the session."""
    from retrieval.descriptors import create_descriptor

    return create_descriptor({"name": "cae"})


@pytest.fixture(scope="session")
def jpeg(sample_dir):
    """``jpeg(i)`` -> the bundled sample's frame ``i`` as JPEG bytes (what a robot sends)."""
    return lambda i: (sample_dir / "image_0" / f"{i:06d}.jpg").read_bytes()


@pytest.fixture(scope="session")
def fleet_demo_run(tmp_path_factory):
    """A short real fleet demo (``cae_lcd.fleet.demo.run_demo``, 40 frames of KITTI 00, two robots): ``(out, summary,
    admin token)``; its state (``out/state``) can be served again with that token."""
    from cae_lcd.cli.fleet_demo import DEFAULT_KITTI
    from cae_lcd.fleet.demo import run_demo

    out = tmp_path_factory.mktemp("fleet_demo")
    token = "demo-admin-secret"
    return out, run_demo(out, DEFAULT_KITTI, frames=40, admin_token=token), token
