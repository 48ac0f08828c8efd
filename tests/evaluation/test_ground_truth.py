"""Ground truth: pairs files, poses files, the pose-derived rule against the shipped loops files."""

from pathlib import Path

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.evaluation.ground_truth import (load_ground_truth, loops_from_poses, pair_matrix, read_loop_pairs,
                                     sniff_ground_truth, up_axis)
from retrieval.detect import SAMPLE_DIR
from retrieval.sequences import read_kitti_poses

SHARED = Path(__file__).resolve().parents[2].parent / "shared"
KITTI = SHARED / "datasets" / "kitti"


def poses_at(xz):
    """(N, 3, 4) identity rotations at the given x-z positions."""
    p = np.zeros((len(xz), 3, 4))
    p[:, :, :3] = np.eye(3)
    p[:, 0, 3], p[:, 2, 3] = np.asarray(xz, float).reshape(-1, 2).T
    return p


def write_poses(path, poses):
    np.savetxt(path, np.asarray(poses).reshape(-1, 12))
    return path


class TestLoopsFromPoses:
    def test_radius_is_strict_and_gap_inclusive(self):
        # frames 0..3 on a line 1 m apart, frame 4 back at 0, frame 5 back at 2
        p = poses_at([[0, 0], [1, 0], [2, 0], [3, 0], [0, 0.0], [2, 0]])
        got = loops_from_poses(p, radius=1.5, min_gap=3)
        assert got.tolist() == [[4, 0], [4, 1], [5, 1], [5, 2]]  # gap 3 is enough: (5, 2)
        assert loops_from_poses(p, radius=1.5, min_gap=4).tolist() == [[4, 0], [5, 1]]
        assert [4, 1] in loops_from_poses(p, radius=1.0 + 1e-9, min_gap=3).tolist()
        assert [4, 1] not in loops_from_poses(p, radius=1.0, min_gap=3).tolist()

    def test_y_is_ignored(self):
        p = poses_at([[0, 0], [0, 0]])
        p[1, 1, 3] = 100.0
        assert loops_from_poses(p, 5.0, 1).tolist() == [[1, 0]]

    def test_time_gap_replaces_frame_gap(self):
        p = poses_at([[0, 0]] * 4)
        t = np.array([0.0, 1.0, 10.0, 10.5])
        assert loops_from_poses(p, 5.0, 1, t, 5.0).tolist() == [[2, 0], [2, 1], [3, 0], [3, 1]]
        with pytest.raises(ConfigError, match="timestamps"):
            loops_from_poses(p, 5.0, 1, t[:3], 5.0)

    def test_empty_and_single(self):
        assert loops_from_poses(np.zeros((0, 3, 4))).shape == (0, 2)
        assert loops_from_poses(poses_at([[0, 0]])).shape == (0, 2)

    def test_chunked_equals_brute_force(self, monkeypatch):
        import cae_lcd.evaluation.ground_truth as g
        rng = np.random.default_rng(1)
        p = poses_at(rng.uniform(0, 30, (300, 2)))
        full = g.loops_from_poses(p, 4.0, 20)
        monkeypatch.setattr(g, "_CHUNK", 7)
        assert np.array_equal(g.loops_from_poses(p, 4.0, 20), full)
        xz = p[:, [0, 2], 3]
        brute = [[i, j] for i in range(300) for j in range(i - 20 + 1) if np.linalg.norm(xz[i] - xz[j]) < 4.0]
        assert full.tolist() == brute

    @pytest.mark.skipif(not KITTI.is_dir(), reason="../shared datasets absent")
    def test_reproduces_sequence_90_loops_exactly(self):
        got = loops_from_poses(read_kitti_poses(KITTI / "poses" / "90.txt"), 5.0, 50)
        want = read_loop_pairs(KITTI / "sequences" / "90" / "loops.txt")
        assert len(want) == 749 and np.array_equal(got, want)
        assert len(np.unique(got[:, 0])) == 100

    def test_reproduces_bundled_sample_loops_exactly(self):
        got = loops_from_poses(read_kitti_poses(SAMPLE_DIR / "poses.txt"), 5.0, 50)
        assert np.array_equal(got, read_loop_pairs(SAMPLE_DIR / "loops.txt"))


class TestSniffGroundTruth:
    def test_kinds(self, tmp_path):
        assert sniff_ground_truth(SAMPLE_DIR / "loops.txt") == "pairs"
        assert sniff_ground_truth(SAMPLE_DIR / "poses.txt") == "poses"
        (tmp_path / "empty.txt").write_text("# no loops\n\n")
        assert sniff_ground_truth(tmp_path / "empty.txt") == "pairs"

    @pytest.mark.parametrize("text", ["1 2 3\n", "1.5 2\n", "a b\n", "1 2\n" + "0 " * 12 + "\n", "0 " * 11])
    def test_rejected(self, tmp_path, text):
        (tmp_path / "gt.txt").write_text(text)
        with pytest.raises(ConfigError, match="not a ground-truth file"):
            sniff_ground_truth(tmp_path / "gt.txt")

    def test_binary_and_missing(self, tmp_path):
        (tmp_path / "gt.bin").write_bytes(b"\x89PNG\xff\xfe\x00")
        with pytest.raises(ConfigError):
            sniff_ground_truth(tmp_path / "gt.bin")
        with pytest.raises(ConfigError, match="not found"):
            sniff_ground_truth(tmp_path / "nope.txt")


class TestLoadGroundTruth:
    def test_pairs_are_ordered_and_unique(self, tmp_path):
        (tmp_path / "gt.txt").write_text("# i j\n3 60\n60 3\n70 5\n")
        gt = load_ground_truth(tmp_path / "gt.txt")
        assert gt.kind == "pairs" and gt.poses is None
        assert gt.pairs.tolist() == [[60, 3], [70, 5]] and gt.queries.tolist() == [60, 70]

    def test_empty_pairs_file(self, tmp_path):
        (tmp_path / "gt.txt").write_text("")
        gt = load_ground_truth(tmp_path / "gt.txt")
        assert gt.pairs.shape == (0, 2) and gt.queries.shape == (0,)

    def test_negative_index(self, tmp_path):
        (tmp_path / "gt.txt").write_text("3 -1\n")
        with pytest.raises(ConfigError, match="negative"):
            load_ground_truth(tmp_path / "gt.txt")

    def test_poses_file_equals_pairs_file(self):
        from_poses = load_ground_truth(SAMPLE_DIR / "poses.txt", 5.0, 50)
        from_pairs = load_ground_truth(SAMPLE_DIR / "loops.txt")
        assert from_poses.kind == "poses" and from_poses.poses.shape == (100, 3, 4)
        assert np.array_equal(from_poses.pairs, from_pairs.pairs)

    def test_poses_options(self, tmp_path):
        path = write_poses(tmp_path / "poses.txt", poses_at([[0, 0], [0, 3], [0, 0]]))
        assert load_ground_truth(path, 5.0, 1).pairs.tolist() == [[1, 0], [2, 0], [2, 1]]
        assert load_ground_truth(path, 2.0, 1).pairs.tolist() == [[2, 0]]
        assert load_ground_truth(path, 5.0, 2).pairs.tolist() == [[2, 0]]
        t = np.array([0.0, 0.5, 9.0])
        assert load_ground_truth(path, 5.0, 1, t, 1.0).pairs.tolist() == [[2, 0], [2, 1]]


class TestPairMatrix:
    def test_symmetric_and_drops_out_of_range(self):
        m = pair_matrix([[2, 0], [9, 1]], 3)
        assert m.shape == (3, 3) and m[2, 0] and m[0, 2] and m.sum() == 2

    def test_empty(self):
        assert pair_matrix(np.zeros((0, 2)), 0).shape == (0, 0)
        assert not pair_matrix(np.zeros((0, 2)), 4).any()


def _quat(R):
    from retrieval.edges import rotation_to_quaternion

    return rotation_to_quaternion(R)


@pytest.mark.parametrize("world", ["y-down", "z-up"])
def test_a_tum_ground_truth_in_either_world_gives_kittis_pairs(kitti_sequences, tmp_path, world, caplog):
    """KITTI 90's poses written as a TUM ``groundtruth.txt`` in a y-down world (evo from KITTI poses) or turned
    z-up: the reader keeps the file's world, the gravity axis is found, and the derived ground truth is KITTI's
    own 749 pairs / 100 queries. Told the wrong world, it warns that the ground truth looks degenerate."""
    from retrieval.run_folder import RunFolder
    from retrieval.sequences import open_sequence
    from retrieval.sequences.base import Z_UP_TO_KITTI

    kitti = open_sequence(kitti_sequences / "90")
    poses = kitti.poses if world == "y-down" else Z_UP_TO_KITTI.T @ kitti.poses
    root = tmp_path / "tum"
    (root / "rgb").mkdir(parents=True)
    lines, truth = [], []
    for t, frame, pose in zip(kitti.timestamps, kitti.frames, poses):
        (root / "rgb" / f"{t:.6f}.png").symlink_to(frame)
        lines.append(f"{t:.6f} rgb/{t:.6f}.png\n")
        truth.append(" ".join(f"{v:.9f}" for v in (t, *pose[:, 3], *_quat(pose[:, :3]))) + "\n")
    (root / "rgb.txt").write_text("".join(lines))
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(truth))
    seq = open_sequence(root)
    np.testing.assert_allclose(seq.poses, poses, atol=1e-4)  # the file's own world
    (tmp_path / "run").mkdir()
    gt_file = RunFolder(tmp_path / "run").write_ground_truth_poses(seq.poses)
    truth = load_ground_truth(gt_file)
    assert truth.up == (1 if world == "y-down" else 2)
    assert len(truth.pairs) == 749 and len(truth.queries) == 100
    np.testing.assert_array_equal(truth.pairs, load_ground_truth(kitti_sequences / "90" / "loops.txt").pairs)
    assert load_ground_truth(gt_file, world=world).pairs.shape == (749, 2)
    caplog.clear()
    wrong = load_ground_truth(gt_file, world="z-up" if world == "y-down" else "y-down")
    assert len(wrong.pairs) != 749 and "likely wrong" in caplog.text


def test_an_unknown_world_is_refused():
    with pytest.raises(ConfigError, match="--world must be one of"):
        up_axis(np.zeros((3, 3, 4)), "x-left")
