"""The EuRoC / ASL reader on the bundled sample laid out as a EuRoC folder (``conftest.euroc_folder``)."""

from __future__ import annotations

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from retrieval.sequences import open_sequence
from retrieval.sequences.base import Z_UP_TO_KITTI


def test_reads_frames_times_intrinsics_and_poses(euroc_folder, sample_seq, assert_same_frames):
    for path in (euroc_folder, euroc_folder / "mav0"):  # the folder holding mav0/, or mav0/ itself
        seq = open_sequence(path)
        assert seq.kind == "euroc" and seq.poses_are_truth
        assert_same_frames(seq)
        np.testing.assert_allclose(seq.K, sample_seq.K)
        np.testing.assert_allclose(seq.timestamps, sample_seq.timestamps + 1000.0, atol=1e-6)
        # in EuRoC's own z-up world (issue 30: no longer turned into KITTI's frame); no T_BS: the body's pose
        np.testing.assert_allclose(seq.poses, Z_UP_TO_KITTI.T @ sample_seq.poses, atol=1e-4)


def test_no_ground_truth_no_poses(euroc_folder, tmp_path):
    import shutil

    copy = tmp_path / "MH"
    shutil.copytree(euroc_folder / "mav0" / "cam0", copy / "mav0" / "cam0")
    seq = open_sequence(copy)
    assert seq.poses is None and not seq.poses_are_truth and seq.K is not None


def test_bad_data_csv_is_one_error(tmp_path):
    cam = tmp_path / "mav0" / "cam0"
    cam.mkdir(parents=True)
    (cam / "data.csv").write_text("#timestamp [ns],filename\n100,a.png\n100;b.png\n")
    with pytest.raises(ConfigError, match=r"data.csv, line 3: expected 'timestamp,file name'"):
        open_sequence(tmp_path)


def test_same_loops_as_the_sample(euroc_folder, sample_loops, detect_like_sample, tmp_path, sample_truth,
                                  assert_frame_keys):
    np.testing.assert_array_equal(detect_like_sample(euroc_folder, tmp_path / "run"), sample_loops)
    # round trip: each row's stamps are data.csv's (ns -> s), its source ids the image paths in the folder
    ns = (sample_truth[:, 0] * 1e9).round().astype(np.int64)
    assert assert_frame_keys(tmp_path / "run", ns * 1e-9, [f"mav0/cam0/data/{t}.jpg" for t in ns]) > 0


def test_sensor_yaml_distortion_and_body_pose_are_read(euroc_folder, tmp_path):
    """EuRoC's own ``sensor.yaml`` (radial-tangential distortion and ``T_BS``) gives the sequence its camera model."""
    import shutil

    copy = tmp_path / "MH"
    shutil.copytree(euroc_folder / "mav0" / "cam0", copy / "mav0" / "cam0")
    (copy / "mav0" / "cam0" / "sensor.yaml").write_text(
        "%YAML:1.0\nsensor_type: camera\nT_BS:\n  cols: 4\n  rows: 4\n  data: [0, -1, 0, -0.02, 1, 0, 0, -0.06, "
        "0, 0, 1, 0.01, 0, 0, 0, 1]\nintrinsics: [458.654, 457.296, 367.215, 248.375]\n"
        "distortion_model: radial-tangential\ndistortion_coefficients: [-0.28340811, 0.07395907, 0.00019359, "
        "1.76187114e-05]\n")
    seq = open_sequence(copy)
    assert seq.camera.model == "radtan" and seq.camera.coefficients[0] == pytest.approx(-0.28340811)
    assert np.allclose(seq.K, seq.camera.K) and seq.K[0, 0] == pytest.approx(458.654)
    assert np.allclose(seq.camera.T_body_camera[:3, 3], [-0.02, -0.06, 0.01])


def test_ground_truth_is_the_cameras_pose_in_euroc_world(euroc_folder, tmp_path):
    """With ``T_BS`` the frames' poses are the camera's (``T_WB T_BS``), in EuRoC's own world, and the run's
    ``ground_truth_poses.txt`` and ``VERTEX_SE3`` lines would carry them as they are."""
    import shutil

    copy = tmp_path / "MH"
    shutil.copytree(euroc_folder, copy)
    sensor = copy / "mav0" / "cam0" / "sensor.yaml"
    sensor.write_text(sensor.read_text() + "T_BS:\n  rows: 4\n  cols: 4\n  data: [0, -1, 0, -0.02, 1, 0, 0, -0.06, "
                                           "0, 0, 1, 0.01, 0, 0, 0, 1]\n")
    body, cam = open_sequence(euroc_folder).poses, open_sequence(copy).poses
    T = np.array([[0, -1, 0, -0.02], [1, 0, 0, -0.06], [0, 0, 1, 0.01], [0, 0, 0, 1.0]])
    np.testing.assert_allclose(cam, body @ T, atol=1e-9)
    np.testing.assert_allclose(cam[:, :, 3], body[:, :, 3] + body[:, :, :3] @ T[:3, 3], atol=1e-9)
