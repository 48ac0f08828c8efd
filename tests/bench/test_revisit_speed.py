"""bench.revisit_speed: the folders of a revisit at another speed, and how their loops are scored."""

from __future__ import annotations

import pytest

from tests.conftest import KITTI_SEQUENCES


@pytest.mark.skipif(not (KITTI_SEQUENCES / "90").is_dir(), reason="shared KITTI data not found")
def test_a_slower_revisit_is_a_sparse_map_then_elsewhere_then_the_second_pass(tmp_path):
    import cv2

    from bench.revisit_speed import ELSEWHERE, speed_folder

    folder, keep = speed_folder(tmp_path, 1 / 3, (64, 32))
    first = list(range(0, 100, 3))  # frames round(3 k): every third one of the first pass, 99 the last
    assert keep == first + [-1] * ELSEWHERE + list(range(100, 200))
    assert len(list(folder.glob("*.png"))) == len(keep)
    assert cv2.imread(str(folder / f"{len(first):06d}.png"), cv2.IMREAD_UNCHANGED).shape == (32, 64)
    _, keep = speed_folder(tmp_path, 2.0, (64, 32))
    assert keep == list(range(100)) + list(range(100, 200, 2))


def test_a_loop_to_a_frame_from_elsewhere_is_false(tmp_path, monkeypatch):
    import numpy as np

    import bench.revisit_speed as R
    from retrieval.run_folder import RunFolder

    if not (R.KITTI90 / "loops.txt").is_file():
        pytest.skip("shared KITTI data not found")
    keep = [0, 3, -1, 100, 101]  # written frame -> KITTI 90 frame (-1: KITTI 07)
    loops = np.array([[3, 0], [4, 2]], np.float64)  # 100 -> 0 (true on KITTI 90's first road), 101 -> KITTI 07
    monkeypatch.setattr(RunFolder, "read_loops", lambda self: loops)
    res = R.scored(tmp_path, keep)
    assert (res["loops"], res["false"], res["off"]) == (2, 1, [])
