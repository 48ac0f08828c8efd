"""Revisits found in an unlabeled folder (issue 28): on real frames, a summer and a winter traversal of one
railway in one folder give pairs that are one place, and a drive without a revisit gives none; the training's
sampling takes them as positives and never as negatives."""

import numpy as np
import pytest

from cae.contrastive import not_revisits, with_revisits
from cae.encode import encode_images
from cae.revisits import fused_similarity, mine_revisits
from cae_lcd.core.images import read_image

from ..conftest import NORDLAND

SUMMER = list(range(100, 200))  # summer frames; frame 500 + t is the same place in winter
OFFSET = len(SUMMER)  # position of the winter frame of summer position p in the folder: p + OFFSET


@pytest.fixture(scope="module")
def railway_codes(encoder):
    """Codes of one folder: 100 summer frames, then the same 100 places in winter (64x32, real)."""
    if not (NORDLAND / "images").is_dir():
        pytest.skip(f"shared Nordland data not found at {NORDLAND}")
    ids = SUMMER + [500 + t for t in SUMMER]
    return encode_images(encoder, [read_image(NORDLAND / "images" / f"{i:06d}.png") for i in ids])


def same_place(i: int, j: int) -> bool:
    """One place: the other season's frame within 2, or two frames of one season (a station stop)."""
    a, b = sorted((i, j))
    return (a < OFFSET) != (b < OFFSET) and abs(b - OFFSET - a) <= 2 or (a < OFFSET) == (b < OFFSET)


def test_summer_and_winter_of_one_railway_are_found_as_one_place(railway_codes):
    n = len(railway_codes)
    pairs = mine_revisits(railway_codes, np.zeros(n, int), np.arange(n), far=20)
    assert len(pairs) >= 60, f"only {len(pairs)} of {n} frames found their other season"
    wrong = [(i, j) for i, j in pairs.tolist() if not same_place(i, j)]
    assert not wrong, wrong[:5]
    assert sum((i < OFFSET) != (j < OFFSET) for i, j in pairs.tolist()) >= 60  # most across the seasons


def test_a_drive_without_revisit_gives_none(encoder, kitti_image):
    codes = encode_images(encoder, [kitti_image("07", i) for i in range(0, 160, 2)])
    n = len(codes)
    assert len(mine_revisits(codes, np.zeros(n, int), np.arange(n), far=10)) == 0


def test_folders_are_searched_apart(railway_codes):
    """The winter half in a folder of its own: no pair crosses folders (a folder is one sequence)."""
    n = len(railway_codes)
    folder = (np.arange(n) >= OFFSET).astype(int)
    position = np.arange(n) % OFFSET
    pairs = mine_revisits(railway_codes, folder, position, far=20)
    assert all(folder[i] == folder[j] for i, j in pairs.tolist())


def test_fused_similarity_averages_each_line():
    rng = np.random.default_rng(0)
    codes = rng.normal(size=(12, 8)).astype(np.float32)
    single, fused = fused_similarity(codes, 0), fused_similarity(codes, 1)
    assert np.isclose(fused[5, 2], np.mean([single[4, 1], single[5, 2], single[6, 3]]), atol=1e-5)
    assert np.isclose(fused[0, 3], np.mean([single[0, 3], single[1, 4]]), atol=1e-5)  # the line's start
    assert fused_similarity(np.zeros((0, 8), np.float32), 2).shape == (0, 0)
    assert mine_revisits(np.zeros((0, 8)), np.zeros(0, int), np.zeros(0, int), far=5).shape == (0, 2)


def test_revisits_are_positives_and_never_negatives():
    revisits = np.array([[0, 7], [3, 9]])
    picks = np.array([0, 3, 7, 8])
    mask = not_revisits(picks, revisits)
    assert not mask[0, 2] and not mask[2, 0]  # 0 and 7 are one place
    assert mask[0, 1] and mask[1, 3] and mask.sum() == 14
    rng = np.random.default_rng(0)
    partners = with_revisits(picks.copy(), picks, revisits, 1.0, rng)
    assert partners.tolist() == [7, 9, 0, 8]  # 8 has no revisit: it keeps its own partner
    assert with_revisits(picks.copy(), picks, revisits, 0.0, rng).tolist() == picks.tolist()
