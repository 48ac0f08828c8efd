"""The video reader on the bundled sample written as a lossless video (``conftest.video_file``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from retrieval.sequences import open_sequence


def test_reads_every_frame_lazily_in_any_order(video_file, assert_same_frames, sample_images):
    seq = open_sequence(video_file)
    assert (seq.kind, seq.K, seq.name) == ("video", None, "sample")
    np.testing.assert_allclose(seq.timestamps, np.arange(100) / 10)
    assert_same_frames(seq)  # in order: no seek
    for i in (93, 4, 5, 60):  # out of order: seeks
        assert np.array_equal(seq.read_frame(i)[0], sample_images[i])
    assert seq.frame_name(4) == "sample.avi:000004"


def test_stride(video_file, sample_images):
    seq = open_sequence(video_file, stride=3)
    assert len(seq) == 34 and seq.frame_name(2) == "sample.avi:000006"
    assert np.array_equal(seq.read_frame(33)[0], sample_images[99])
    np.testing.assert_allclose(seq.timestamps[:3], [0.0, 0.3, 0.6])


def test_bad_options_are_one_error(video_file, sample_dir, tmp_path):
    with pytest.raises(ConfigError, match="--stride must be an integer from 1 to"):
        open_sequence(video_file, stride=0)
    with pytest.raises(ConfigError, match="is a folder sequence: --stride"):
        open_sequence(sample_dir, stride=2)
    with pytest.raises(ConfigError, match="is a video sequence: --topic"):
        open_sequence(video_file, topic="/cam0/image_raw")
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    with pytest.raises(ConfigError, match="cannot open video|holds no frame"):
        open_sequence(tmp_path / "broken.mp4")


def test_same_loops_as_the_sample(video_file, sample_loops, detect_like_sample, tmp_path, assert_frame_keys):
    """A lossless video of the sample: the frames are the sample's, so are the loops (read lazily, in order)."""
    np.testing.assert_array_equal(detect_like_sample(video_file, tmp_path / "run"), sample_loops)
    n = 100  # 10 fps: frame i at i / 10 s, its source id the video's frame number
    assert assert_frame_keys(tmp_path / "run", np.arange(n) / 10, [str(i) for i in range(n)]) > len(sample_loops)


def test_a_strided_video_keeps_the_videos_frame_numbers(kitti_sequences, tmp_path, assert_frame_keys):
    """KITTI 90 as a lossless 10 fps video, ``detect video --stride 2``: the rows carry the video's frame numbers
    (2 x the run's ids) and stamps, and scoring against the video's own ground truth (KITTI 90's ``loops.txt``,
    numbered by its frames) counts every loop right."""
    import json

    from cae_lcd.cli.main import main
    from retrieval.run_folder import RunFolder

    seq = open_sequence(kitti_sequences / "90")
    video = tmp_path / "kitti90.avi"
    first = seq.read_frame(0)[0]
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 10, first.shape[::-1], isColor=False)
    for i in range(len(seq)):
        writer.write(seq.read_frame(i)[0])
    writer.release()
    out = tmp_path / "run"
    assert main(["detect", str(video), "--stride", "2", "--out", str(out), "--no-progress"]) == 0
    loops = RunFolder(out).read_loops()
    assert len(loops) > 30
    assert assert_frame_keys(out, np.arange(100) * 2 / 10, [str(2 * i) for i in range(100)]) > len(loops)
    assert main(["evaluate", str(out), "--gt", str(seq.ground_truth)]) == 0
    op = json.loads((out / "evaluation.json").read_text())["operating_point"]
    assert op["precision"] == 1.0 and op["recall"] >= 0.9
    assert json.loads(RunFolder(out).summary.read_text())["stride"] == 2


@pytest.mark.parametrize("fourcc, ext", [("MJPG", ".avi"), ("mp4v", ".mp4"), ("FFV1", ".avi")])
def test_a_one_frame_video_reads_its_frame_again(tmp_path, sample_images, fourcc, ext):
    """Read once by the calibration's pass and again by the run: the seek back to frame 0 failed in a one-frame
    MJPG or MPEG-4 video (the run skipped its only frame as unreadable)."""
    path = tmp_path / f"one{ext}"
    h, w = sample_images[0].shape
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (w, h), isColor=False)
    assert writer.isOpened()
    writer.write(sample_images[0])
    writer.release()
    seq = open_sequence(path)
    assert len(seq) == 1
    first = seq.read_frame(0)[0]
    assert isinstance(first, np.ndarray)
    for _ in range(2):
        again, _ = seq.read_frame(0)
        assert isinstance(again, np.ndarray) and np.array_equal(again, first)


def test_a_broken_or_cut_video_prints_no_ffmpeg_lines(tmp_path, sample_images):
    """FFmpeg printed its own lines to stderr for each damaged packet; now only the project's messages. Run in a
    fresh process: FFmpeg reads its log level when OpenCV first opens a video."""
    import subprocess
    import sys

    h, w = sample_images[0].shape
    writer = cv2.VideoWriter(str(tmp_path / "whole.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h), isColor=False)
    for image in sample_images[:20]:
        writer.write(image)
    writer.release()
    data = (tmp_path / "whole.avi").read_bytes()
    (tmp_path / "cut.avi").write_bytes(data[: len(data) // 2])
    (tmp_path / "fake.mp4").write_text("not a video")
    script = ("import sys\nfrom retrieval.sequences import open_sequence\n"
              f"seq = open_sequence({str(tmp_path / 'cut.avi')!r})\n"
              "bad = sum(not hasattr(seq.read_frame(i)[0], 'shape') for i in range(len(seq)))\n"
              "print(bad)\n"
              f"try:\n    open_sequence({str(tmp_path / 'fake.mp4')!r})\nexcept Exception as err:\n    print(err)\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "OPENCV_FFMPEG_LOGLEVEL"}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env,
                          cwd=Path(__file__).parents[3])
    assert proc.returncode == 0, proc.stderr
    bad, refused = proc.stdout.splitlines()
    assert int(bad) > 0 and "cannot open video" in refused  # the cut frames are reported, the fake refused
    assert proc.stderr == ""
