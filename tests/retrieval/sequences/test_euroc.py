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


def test_edges_in_the_body_frame_round_trip(euroc_folder, tmp_path, detect_like_sample):
    """``detect --edge-frame body --metric-edges`` on a EuRoC folder whose ``sensor.yaml`` has a turned, offset
    ``T_BS`` and whose ground truth is the body's (``T_WC T_BS^-1``): the edges and the g2o vertices are the
    bodies' (each edge within 1 degree and 0.1 m of the ground truth's relative body pose; the camera's edges
    would be a metre off: the camera's translation in the body's axes), the JSON says so."""
    import json
    import shutil

    from retrieval.edges import edge_errors, rotation_to_quaternion
    from retrieval.run_folder import RunFolder

    X = np.array([[0, -1, 0, -0.02], [1, 0, 0, -0.06], [0, 0, 1, 0.3], [0, 0, 0, 1.0]])  # camera -> body
    copy = tmp_path / "MH"
    shutil.copytree(euroc_folder, copy)
    sensor = copy / "mav0" / "cam0" / "sensor.yaml"
    sensor.write_text(sensor.read_text() + "T_BS:\n  rows: 4\n  cols: 4\n  data: [" + ", ".join(
        f"{v:g}" for v in X.ravel()) + "]\n")
    cameras = open_sequence(euroc_folder).poses  # the fixture's ground truth is the camera's
    bodies = cameras @ np.linalg.inv(X)
    truth = copy / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = truth.read_text().splitlines()
    rows = []
    for line, B in zip(lines[1:], bodies):
        x, y, z, w = rotation_to_quaternion(B[:, :3])
        rows.append(",".join([line.split(",")[0], *(f"{v:.12f}" for v in (*B[:, 3], w, x, y, z))]
                             + line.split(",")[8:]))
    truth.write_text("\n".join([lines[0], *rows]) + "\n")
    np.testing.assert_allclose(open_sequence(copy).poses, cameras, atol=1e-9)  # T_WB T_BS: the camera's again

    detect_like_sample(copy, tmp_path / "run", "--edge-frame", "body", "--metric-edges")
    run = RunFolder(tmp_path / "run")
    edges = run.read_edge_list()
    assert len(edges) > 20 and all(e.metric for e in edges)
    errors = edge_errors(edges, bodies)
    assert errors[:, 0].max() < 1.0
    for e in edges:
        Bm, Bq = (np.vstack([bodies[i], [0, 0, 0, 1]]) for i in (e.match, e.query))
        assert np.linalg.norm(e.t - (np.linalg.inv(Bm) @ Bq)[:3, 3]) < 0.1, (e.query, e.match)
    vertices = {int(ln.split()[1]): np.array(ln.split()[2:5], float)
                for ln in run.edges_g2o.read_text().splitlines() if ln.startswith("VERTEX_SE3")}
    assert vertices and all(np.allclose(p, bodies[i][:, 3], atol=1e-6) for i, p in vertices.items())
    written = json.loads(run.edges_json.read_text())
    assert written["frame"] == "body" and np.allclose(written["T_body_camera"], X)
    assert json.loads(run.summary.read_text())["edge_frame"] == "body"
