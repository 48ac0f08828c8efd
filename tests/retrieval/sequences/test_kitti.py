import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.evaluation.ground_truth import read_loop_pairs
from retrieval.sequences import Sequence, open_sequence, read_kitti_calib, read_kitti_poses


class TestOpenSequence:
    def test_bundled_sample(self, sample_dir):
        seq = open_sequence(sample_dir)
        assert isinstance(seq, Sequence) and seq.kind == "kitti"
        assert len(seq) == 100
        assert seq.frames[0].name == "000000.jpg" and seq.frames[-1].name == "000099.jpg"
        np.testing.assert_allclose(seq.K, [[359.428, 0, 303.3464], [0, 359.428, 92.35785], [0, 0, 1]])
        assert seq.timestamps.shape == (100,) and np.all(np.diff(seq.timestamps) > 0)
        assert seq.poses.shape == (100, 3, 4)
        assert seq.ground_truth == sample_dir / "loops.txt"
        loops = read_loop_pairs(seq.ground_truth)
        assert loops.shape == (111, 2)
        assert (loops[:, 0] > loops[:, 1]).all()
        assert [55, 5] in loops.tolist()
        assert len(np.unique(loops[:, 0])) == 50  # 50 queries with a true loop (sample README)
        # ground truth agrees with the poses: every pair is < 5 m apart on the ground plane
        d = np.linalg.norm(seq.poses[loops[:, 0]][:, [0, 2], 3] - seq.poses[loops[:, 1]][:, [0, 2], 3], axis=1)
        assert d.max() < 5.0

    def test_shared_kitti_90(self, kitti_sequences):
        seq = open_sequence(kitti_sequences / "90")
        assert len(seq) == 200 and seq.kind == "kitti"
        assert seq.poses.shape == (200, 3, 4)  # from ../../poses/90.txt
        assert read_loop_pairs(seq.ground_truth).shape == (749, 2)
        assert seq.K[0, 0] == pytest.approx(718.856)

    def test_shared_kitti_07(self, kitti_sequences):
        seq = open_sequence(kitti_sequences / "07")
        assert len(seq) == 160 and seq.ground_truth is None
        assert seq.timestamps.shape == (160,) and seq.poses.shape == (160, 3, 4)

    def test_plain_folder(self, tmp_path, copy_sample_frames):
        copy_sample_frames([2, 0, 1], tmp_path)
        (tmp_path / "notes.txt").write_text("not an image")
        seq = open_sequence(tmp_path)
        assert seq.kind == "folder" and len(seq) == 3
        assert [p.name for p in seq.frames] == ["000000.jpg", "000001.jpg", "000002.jpg"]
        assert seq.K is None and seq.timestamps is None and seq.poses is None and seq.ground_truth is None
        (tmp_path / "loops.txt").write_text("2 0\n")  # its own ground truth: what ``cae-lcd evaluate RUN`` reads
        assert open_sequence(tmp_path).ground_truth == tmp_path / "loops.txt"

    def test_metadata_of_wrong_length_ignored(self, tmp_path, copy_sample_frames, sample_dir, caplog):
        copy_sample_frames([0, 1, 2], tmp_path / "image_0")
        (tmp_path / "times.txt").write_text("0.0\n0.1\n")  # 2 times for 3 frames
        (tmp_path / "calib.txt").write_text((sample_dir / "calib.txt").read_text())
        seq = open_sequence(tmp_path)
        assert seq.kind == "kitti" and len(seq) == 3
        assert seq.timestamps is None and seq.K is not None
        assert "ignoring" in caplog.text

    def test_missing_folder(self, tmp_path):
        with pytest.raises(ConfigError, match="not found"):
            open_sequence(tmp_path / "missing")

    def test_empty_folders(self, tmp_path):
        with pytest.raises(ConfigError, match="no images"):
            open_sequence(tmp_path)
        (tmp_path / "image_0").mkdir()
        with pytest.raises(ConfigError, match="no images"):
            open_sequence(tmp_path)

    def test_missing_camera(self, sample_dir):
        with pytest.raises(ConfigError, match="image_2"):
            open_sequence(sample_dir, camera="image_2")


class TestReadKittiCalib:
    def test_cameras(self, sample_dir):
        K = read_kitti_calib(sample_dir / "calib.txt")
        assert K.shape == (3, 3) and K[2].tolist() == [0, 0, 1]
        with pytest.raises(ConfigError, match="P2:"):
            read_kitti_calib(sample_dir / "calib.txt", "image_2")


class TestReadKittiPoses:
    def test_shape_and_errors(self, sample_dir, tmp_path):
        poses = read_kitti_poses(sample_dir / "poses.txt")
        assert poses.shape == (100, 3, 4)
        np.testing.assert_allclose(poses[0][:, :3], np.eye(3), atol=1e-6)
        (tmp_path / "bad.txt").write_text("1 2 3\n4 5 6\n")
        with pytest.raises(ConfigError, match="12 numbers"):
            read_kitti_poses(tmp_path / "bad.txt")


class TestReadLoopPairs:
    def test_order_comments_empty(self, tmp_path):
        (tmp_path / "l.txt").write_text("# i j\n5 55\n60 7\n\n")
        np.testing.assert_array_equal(read_loop_pairs(tmp_path / "l.txt"), [[55, 5], [60, 7]])
        (tmp_path / "e.txt").write_text("# nothing\n")
        pairs = read_loop_pairs(tmp_path / "e.txt")
        assert pairs.shape == (0, 2)
