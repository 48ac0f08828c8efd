"""The bag reader on the bundled sample written as ROS 2 (sqlite3, mcap) and ROS 1 bags with ``rosbags``."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import ImageError
from retrieval.sequences import open_sequence
from retrieval.sequences.rosbag import COMPRESSED, IMAGE, image_from_message, write_image_bag

TOPIC = "/cam0/image_raw"


@pytest.fixture(scope="module")
def bags(tmp_path_factory, sample_seq, sample_images):
    """ROS 2 (sqlite3 folder, with CameraInfo), ROS 2 mcap (without) and ROS 1 (with) bags of the sample."""
    root = tmp_path_factory.mktemp("bags")
    t = sample_seq.timestamps + 1000.0
    write_image_bag(root / "ros2", sample_images, t, TOPIC, K=sample_seq.K)
    write_image_bag(root / "ros2.mcap", sample_images, t, TOPIC)
    write_image_bag(root / "ros1.bag", sample_images, t, TOPIC, K=sample_seq.K, ros1=True)
    return root


@pytest.mark.parametrize("name, storage, has_K", [("ros2", None, True), ("ros2", "*.db3", True),
                                                  ("ros2.mcap", "*.mcap", False), ("ros1.bag", None, True)])
def test_reads_frames_stamps_and_camera_info(bags, name, storage, has_K, sample_seq, assert_same_frames):
    path = bags / name
    if storage:  # a ROS 2 bag is a folder; its one storage file (.db3, .mcap) alone is a bag too
        path = next(path.glob(storage))
    seq = open_sequence(path, topic=TOPIC)
    assert seq.kind == "rosbag" and seq.frame_name(3).startswith(TOPIC + "@")
    assert_same_frames(seq)
    np.testing.assert_allclose(seq.timestamps, sample_seq.timestamps + 1000.0, atol=1e-6)
    if has_K:
        np.testing.assert_allclose(seq.K, sample_seq.K)
    else:
        assert seq.K is None


@pytest.mark.parametrize("name", ["ros2", "ros2.mcap", "ros1.bag"])
def test_same_loops_as_the_sample(bags, name, sample_loops, detect_like_sample, tmp_path, sample_seq,
                                  assert_frame_keys):
    """``cae-lcd detect rec --topic /cam0/image_raw`` reads the bag lazily through the detector (ROS 2 sqlite3 and
    mcap, ROS 1)."""
    np.testing.assert_array_equal(detect_like_sample(bags / name, tmp_path / "run", "--topic", TOPIC), sample_loops)
    # round trip: each row's stamps are the messages' header stamps, its source ids their index on the topic
    times = sample_seq.timestamps + 1000.0
    assert assert_frame_keys(tmp_path / "run", times, [str(i) for i in range(len(times))]) > len(sample_loops)


def test_camera_info_distortion_is_read(tmp_path, sample_seq, sample_images):
    """A bag whose ``CameraInfo`` has an equidistant ``D``: the sequence's camera has it (``detect`` undistorts the
    keypoints with it)."""
    D = np.array([0.01, -0.02, 0.003, -0.001])
    write_image_bag(tmp_path / "fish", sample_images[:3], np.arange(3) + 1.0, TOPIC, K=sample_seq.K,
                    distortion=("equidistant", D))
    seq = open_sequence(tmp_path / "fish", topic=TOPIC)
    assert seq.camera.model == "equidistant" and np.allclose(seq.camera.coefficients, D)
    assert np.allclose(seq.K, sample_seq.K) and seq.source_id(2) == "2"


def test_topic_errors(bags):
    assert open_sequence(bags / "ros2").stream.topic == TOPIC  # no --topic: the bag's only image topic
    with pytest.raises(ConfigError, match=r"has no image topic /nope; image topics: /cam0/image_raw"):
        open_sequence(bags / "ros2", topic="/nope")
    with pytest.raises(ConfigError, match="is a rosbag sequence: --camera"):
        open_sequence(bags / "ros2", camera="image_0")


def _message(image: np.ndarray, encoding: str, big: bool = False) -> SimpleNamespace:
    data = image.astype(image.dtype.newbyteorder(">" if big else "<")).tobytes()
    return SimpleNamespace(encoding=encoding, height=image.shape[0], width=image.shape[1], is_bigendian=int(big),
                           step=len(data) // image.shape[0], data=np.frombuffer(data, np.uint8))


def test_encodings(sample_images):
    grey = sample_images[0]
    bgr = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    bgr[..., 2] //= 2  # tell the channels apart
    assert np.array_equal(image_from_message(_message(grey, "mono8"), IMAGE, "m")[0], grey)
    assert np.array_equal(image_from_message(_message(bgr, "bgr8"), IMAGE, "m")[0], bgr)
    assert np.array_equal(image_from_message(_message(bgr[..., ::-1].copy(), "rgb8"), IMAGE, "m")[0], bgr)
    deep = grey.astype(np.uint16) * 257
    assert np.array_equal(image_from_message(_message(deep, "mono16", big=True), IMAGE, "m")[0], deep)
    bayer = image_from_message(_message(grey, "bayer_rggb8"), IMAGE, "m")[0]
    assert bayer.shape == (*grey.shape, 3)
    jpeg = cv2.imencode(".png", grey)[1]
    assert np.array_equal(image_from_message(SimpleNamespace(data=jpeg), COMPRESSED, "m")[0], grey)
    with pytest.raises(ImageError, match="unsupported encoding 'yuv422'"):
        image_from_message(_message(grey, "yuv422"), IMAGE, "m")
    short = _message(grey, "mono8")
    short.data = short.data[:100]
    with pytest.raises(ImageError, match="do not hold"):
        image_from_message(short, IMAGE, "m")
