"""The stream benchmark and its augmented real frames: shapes, determinism, and one tiny stream."""

import json

import numpy as np
import pytest

from bench.augment import augment, augmented_frames, shared_frames
from bench.stream import main as stream_main


@pytest.fixture(scope="module")
def kitti():
    paths = shared_frames(kitti_only=True)
    if not paths:
        pytest.skip("../shared/datasets not present")
    return paths


def test_augment_keeps_shape_and_changes_pixels(kitti):
    from cae_lcd.core.images import read_image

    img = read_image(kitti[0])
    a, b = augment(img, np.random.default_rng(1)), augment(img, np.random.default_rng(1))
    assert a.shape == img.shape and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)  # seeded
    assert np.abs(a.astype(int) - img).mean() > 1.0


def test_augmented_frames_real_first_then_augmented(kitti):
    out = list(augmented_frames(kitti[:2], 4, seed=0))
    assert [p for p, _ in out] == [kitti[0], kitti[1], kitti[0], kitti[1]]
    np.testing.assert_array_equal(out[0][1], out[0][1])
    assert not np.array_equal(out[0][1], out[2][1])  # the second pass is augmented


def test_tiny_stream_writes_points_and_table(kitti, tmp_path):
    res = stream_main(frames=4, out=tmp_path / "s", window=2)
    assert [p["frames"] for p in res["points"]] == [2, 4]
    assert res["points"][-1]["keyframes"] == 4 and res["store_bytes_per_frame"] > 0
    assert json.loads((tmp_path / "s" / "stream.json").read_text())["frames"] == 4
    assert "last / first window median" in (tmp_path / "s" / "stream.md").read_text()
    assert (tmp_path / "s" / "stream.png").stat().st_size > 0
