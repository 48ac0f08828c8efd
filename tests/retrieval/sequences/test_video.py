"""The video reader on the bundled sample written as a lossless video (``conftest.video_file``)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from core.conf import ConfigError
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
    with pytest.raises(ConfigError, match="--stride must be an integer >= 1"):
        open_sequence(video_file, stride=0)
    with pytest.raises(ConfigError, match="is a folder sequence: --stride"):
        open_sequence(sample_dir, stride=2)
    with pytest.raises(ConfigError, match="is a video sequence: --topic"):
        open_sequence(video_file, topic="/cam0/image_raw")
    (tmp_path / "broken.mp4").write_bytes(b"not a video")
    with pytest.raises(ConfigError, match="cannot open video|holds no frame"):
        open_sequence(tmp_path / "broken.mp4")


def test_same_loops_as_the_sample(video_file, sample_loops, detect_like_sample, tmp_path):
    """A lossless video of the sample: the frames are the sample's, so are the loops (read lazily, in order)."""
    np.testing.assert_array_equal(detect_like_sample(video_file, tmp_path / "run"), sample_loops)


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
