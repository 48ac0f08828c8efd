"""Fixtures: the bundled sample laid out as each input layout (ROS 2 and ROS 1 bags written with ``rosbags``, TUM
and EuRoC folders, a lossless video), and the loops of the sample itself to compare with. Built once a session."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from retrieval.run_folder import RunFolder
from retrieval.sequences.base import Z_UP_TO_KITTI


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """A rotation matrix ``(3, 3)`` -> unit quaternion ``(x, y, z, w)`` (Shepperd's method)."""
    t = np.trace(R)
    if t > 0:
        s = 2 * np.sqrt(1 + t)
        q = [(R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s, s / 4]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2 * np.sqrt(1 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i], q[j], q[k] = s / 4, (R[j, i] + R[i, j]) / s, (R[k, i] + R[i, k]) / s
    return np.array(q)


@pytest.fixture(scope="session")
def sample_truth(sample_seq):
    """The sample's timestamps ``(N,)`` and poses ``(N, 3, 4)`` as a z-up trajectory ``(N, 8)``: ``t, xyz, xyzw``."""
    poses = Z_UP_TO_KITTI.T @ sample_seq.poses  # the inverse of what the TUM / EuRoC readers apply
    quats = np.stack([matrix_to_quat(p[:, :3]) for p in poses])
    return np.column_stack([sample_seq.timestamps + 1000.0, poses[:, :, 3], quats])


@pytest.fixture(scope="session")
def tum_folder(tmp_path_factory, sample_seq, sample_truth) -> Path:
    """The sample as a TUM RGB-D folder: ``rgb/<t>.jpg`` (the sample's files), ``rgb.txt``, ``groundtruth.txt``."""
    root = tmp_path_factory.mktemp("tum") / "rgbd_sample"
    (root / "rgb").mkdir(parents=True)
    lines = []
    for t, frame in zip(sample_truth[:, 0], sample_seq.frames):
        shutil.copyfile(frame, root / "rgb" / f"{t:.6f}.jpg")
        lines.append(f"{t:.6f} rgb/{t:.6f}.jpg")
    (root / "rgb.txt").write_text("# color images\n# timestamp filename\n" + "\n".join(reversed(lines)) + "\n")
    rows = "\n".join(" ".join(f"{v:.9f}" for v in r) for r in sample_truth)
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + rows + "\n")
    return root


@pytest.fixture(scope="session")
def euroc_folder(tmp_path_factory, sample_seq, sample_truth) -> Path:
    """The sample as a EuRoC / ASL folder: ``mav0/cam0/{data/<ns>.jpg, data.csv, sensor.yaml}`` and
    ``mav0/state_groundtruth_estimate0/data.csv`` (q as w, x, y, z; velocities and biases zero)."""
    root = tmp_path_factory.mktemp("euroc") / "MH_sample"
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    ns = (sample_truth[:, 0] * 1e9).round().astype(np.int64)
    for t, frame in zip(ns, sample_seq.frames):
        shutil.copyfile(frame, cam / "data" / f"{t}.jpg")
    (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{t},{t}.jpg\n" for t in ns))
    K = sample_seq.K
    (cam / "sensor.yaml").write_text(f"%YAML:1.0\nsensor_type: camera\nintrinsics: [{K[0, 0]}, {K[1, 1]}, "
                                     f"{K[0, 2]}, {K[1, 2]}]\n")
    gt = root / "mav0" / "state_groundtruth_estimate0"
    gt.mkdir()
    rows = [[t, *r[1:4], r[7], *r[4:7], *[0.0] * 9] for t, r in zip(ns, sample_truth)]
    (gt / "data.csv").write_text("#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], "
                                 "q_RS_y [], q_RS_z [], v..., b_w..., b_a...\n"
                                 + "".join(",".join(f"{v:.9f}" if k else str(v) for k, v in enumerate(r)) + "\n"
                                           for r in rows))
    return root


@pytest.fixture(scope="session")
def sample_images(sample_seq) -> list[np.ndarray]:
    """The sample's 100 frames, decoded (grey uint8)."""
    return [sample_seq.read_frame(i)[0] for i in range(len(sample_seq))]


@pytest.fixture(scope="session")
def video_file(tmp_path_factory, sample_images) -> Path:
    """The sample as a lossless (FFV1) grey video, 10 fps."""
    path = tmp_path_factory.mktemp("video") / "sample.avi"
    h, w = sample_images[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 10, (w, h), isColor=False)
    assert writer.isOpened()
    for image in sample_images:
        writer.write(image)
    writer.release()
    return path


@pytest.fixture(scope="session")
def sample_loops(cli_sample_run) -> np.ndarray:
    """``(L, 2)`` the loops the bundled sample itself gives (``cae-lcd detect`` on it)."""
    code, out = cli_sample_run
    assert code == 0
    return RunFolder(out).read_loops()[:, :2]


@pytest.fixture(scope="session")
def assert_same_frames(sample_images):
    """``assert_same_frames(seq)``: ``seq`` gives the sample's frames pixel for pixel (as ``detect`` reads them)."""

    def check(seq) -> None:
        assert len(seq) == len(sample_images)
        for i, image in enumerate(sample_images):
            got = seq.read_frame(i)[0]
            assert isinstance(got, np.ndarray) and got.shape == image.shape and np.array_equal(got, image), i

    return check


@pytest.fixture(scope="session")
def detect_like_sample(cli_sample_run):
    """``detect_like_sample(path, out, *args)``: ``cae-lcd detect path`` into ``out``, seeded with the sample run's
    calibration (what detect would compute again from the same pixels: saves a calibration per test), returning
    its loops ``(L, 2)``."""
    from cae_lcd.cli.main import main

    def run(path, out: Path, *args: str) -> np.ndarray:
        out.mkdir(parents=True)
        shutil.copyfile(RunFolder(cli_sample_run[1]).calibration, RunFolder(out).calibration)
        assert main(["detect", str(path), "--out", str(out), "--no-progress", *args]) == 0
        return RunFolder(out).read_loops()[:, :2]

    return run


@pytest.fixture(scope="session")
def assert_frame_keys():
    """``assert_frame_keys(run_dir, times, sources)``: ``_frame_keys_match``."""
    return _frame_keys_match


def _frame_keys_match(run_dir: Path, times: np.ndarray, sources: list[str]) -> int:
    """Every row of the run's ``loops.csv``, ``candidates.csv`` and ``loop_edges.csv`` carries its frames' stamps
    ``times[id]`` and source ids ``sources[id]``, and ``loops_tum.txt`` the loops' stamps; returns the rows checked."""
    import csv

    run = RunFolder(run_dir)
    checked = 0
    for path, other in ((run.loops, "match"), (run.candidates, "candidate"), (run.edges_csv, "match")):
        for row in csv.DictReader(open(path, newline="")):
            q, m = int(row["query"]), int(row[other])
            assert float(row["query_time"]) == pytest.approx(times[q], abs=1e-6), (path.name, q)
            assert float(row[f"{other}_time"]) == pytest.approx(times[m], abs=1e-6), (path.name, m)
            assert (row["query_source"], row[f"{other}_source"]) == (sources[q], sources[m]), path.name
            checked += 1
    loops = run.read_loops()[:, :2].astype(int)
    tum = np.loadtxt(run.loops_tum, ndmin=2)
    np.testing.assert_allclose(tum, times[loops], atol=1e-6)
    return checked
