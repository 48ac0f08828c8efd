"""The TUM RGB-D reader on the bundled sample laid out as a TUM folder (``conftest.tum_folder``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cae_lcd.cli.main import main
from cae_lcd.core.conf import ConfigError
from retrieval.run_folder import RunFolder
from retrieval.sequences import open_sequence
from retrieval.sequences.base import Z_UP_TO_KITTI


def test_reads_frames_times_and_poses(tum_folder, sample_seq, assert_same_frames):
    seq = open_sequence(tum_folder)
    assert (seq.kind, seq.K) == ("tum", None)
    assert_same_frames(seq)  # rgb.txt's order is by time, not by line
    np.testing.assert_allclose(seq.timestamps, sample_seq.timestamps + 1000.0)
    # in the file's own z-up world (issue 30: no longer turned into KITTI's frame)
    np.testing.assert_allclose(seq.poses, Z_UP_TO_KITTI.T @ sample_seq.poses, atol=1e-4)
    assert seq.poses_are_truth


def test_same_loops_as_the_sample_and_scored_from_poses(tum_folder, sample_loops, detect_like_sample, tmp_path,
                                                        sample_truth, assert_frame_keys):
    out = tmp_path / "run"
    np.testing.assert_array_equal(detect_like_sample(tum_folder, out), sample_loops)
    # round trip: each row's stamps are rgb.txt's, its source ids the image paths rgb.txt lists
    times = sample_truth[:, 0]
    assert assert_frame_keys(out, times, [f"rgb/{t:.6f}.jpg" for t in times]) > len(sample_loops)
    summary = json.loads(RunFolder(out).summary.read_text())
    assert summary["ground_truth_file"] == str(RunFolder(out).ground_truth_poses)
    assert summary["ground_truth"]["precision"] == 1.0 and summary["ground_truth"]["recall"] >= 0.9
    assert main(["evaluate", str(out)]) == 0  # no --gt: derived from the recording's poses
    report = json.loads((out / "evaluation.json").read_text())
    assert report["ground_truth"]["kind"] == "poses" and report["operating_point"]["precision"] == 1.0


def test_bad_rgb_txt_is_one_error(tmp_path):
    (tmp_path / "rgb.txt").write_text("1.0 rgb/a.png\nnot-a-time rgb/b.png\n")
    with pytest.raises(ConfigError, match=r"rgb.txt, line 2: expected 'timestamp file name'"):
        open_sequence(tmp_path)
