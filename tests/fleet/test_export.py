"""Trajectories out of the fleet (``cae_lcd.fleet.export``): TUM and KITTI files that ``evo`` reads, and ``evo_ape`` on the
fleet demo's exported trajectory against KITTI ground truth gives the demo's own RMSE."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cae_lcd.cli.fleet_demo import DEFAULT_KITTI
from cae_lcd.core.conf import ConfigError
from cae_lcd.fleet.export import format_trajectory, trajectory_rows, write_trajectory
from retrieval.sequences import read_kitti_poses, read_times

EVO_APE = Path(sys.executable).with_name("evo_ape")


@pytest.fixture(scope="module")
def kitti00():
    """Real KITTI 00 ground truth: ``(times (200,), poses (200, 3, 4))``."""
    return (read_times(DEFAULT_KITTI / "sequences" / "00" / "times.txt"),
            read_kitti_poses(DEFAULT_KITTI / "poses" / "00.txt"))


def evo_ape_rmse(fmt: str, reference: Path, estimate: Path) -> float:
    """``evo_ape FMT REF EST`` (no alignment, translation part) -> its RMSE."""
    res = subprocess.run([str(EVO_APE), fmt, str(reference), str(estimate)], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    return float(re.search(r"rmse\s+([0-9.eE+-]+)", res.stdout).group(1))


def test_evo_reads_both_formats_back(tmp_path, kitti00):
    from evo.tools import file_interface

    times, poses = kitti00[0][:30], kitti00[1][:30]
    tum = file_interface.read_tum_trajectory_file(str(write_trajectory(tmp_path / "t.tum", times, poses, "tum")))
    kitti = file_interface.read_kitti_poses_file(str(write_trajectory(tmp_path / "t.kitti", times, poses, "kitti")))
    for traj in (tum, kitti):
        assert np.allclose(traj.positions_xyz, poses[:, :, 3], atol=1e-6)
        assert np.allclose(np.stack(traj.poses_se3)[:, :3, :3], poses[:, :, :3], atol=1e-6)
    assert np.allclose(tum.timestamps, times, atol=1e-6)


@pytest.mark.parametrize("fmt, times, poses", [("g2o", 1, 1), ("tum", 2, 1), ("kitti", 1, np.nan)])
def test_bad_trajectories_are_refused(kitti00, fmt, times, poses):
    P = kitti00[1][:1] * poses
    with pytest.raises(ConfigError):
        format_trajectory(kitti00[0][:times], P, fmt)


def test_rows_follow_keyframe_order_and_skip_unknown_stamps(kitti00):
    poses = {5: np.eye(4), 1: 2 * np.eye(4), 9: 3 * np.eye(4)}
    ids, times, P = trajectory_rows(poses, {1: 0.1, 5: 0.5})
    assert ids.tolist() == [1, 5] and times.tolist() == [0.1, 0.5] and P[0, 0, 0] == 2


def test_evo_ape_on_the_demo_export_gives_the_demo_rmse(fleet_demo_run, kitti00, tmp_path):
    out, summary, _ = fleet_demo_run
    assert summary["merged"]
    folder = out / "trajectories"
    assert set(summary["trajectories"]) == {"A.tum", "A.kitti", "B.tum", "B.kitti"}
    gt_tum = write_trajectory(tmp_path / "00.tum", *kitti00, "tum")  # evo associates by timestamp
    b_frames = list(range(1, 40, 2))
    gt_b_kitti = write_trajectory(tmp_path / "00_B.kitti", kitti00[0][b_frames], kitti00[1][b_frames], "kitti")
    expected = summary["merged_b_rmse_m"]
    assert evo_ape_rmse("tum", gt_tum, folder / "B.tum") == pytest.approx(expected, rel=1e-4, abs=1e-6)
    assert evo_ape_rmse("kitti", gt_b_kitti, folder / "B.kitti") == pytest.approx(expected, rel=1e-4, abs=1e-6)
