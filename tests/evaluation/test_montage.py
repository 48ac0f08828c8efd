"""Montages of accepted and missed loops (``cae_lcd.evaluation.montage``) on the bundled sample's real frames: wrong loops
framed red, correct ones green, missed ones orange, and ``evaluate`` writes both pictures."""

from __future__ import annotations

import cv2
import numpy as np

from cae_lcd.evaluation import evaluate
from cae_lcd.evaluation.montage import BORDER, COLOURS, MAX_PAIRS, missed_pairs, pick_pairs, write_montage
from retrieval.detect import SAMPLE_DIR

TRUE_PAIR, FAR_PAIR = (55, 5), (55, 30)  #: a real revisit of the sample, and two frames far apart


def frame_colour(image: np.ndarray, cell: int, cell_width: int) -> np.ndarray:
    """The colour of cell ``cell``'s left frame (cells of ``cell_width`` pixels, padded by 2, under a 30-px head)."""
    x = (cell % 2) * cell_width + 2 + BORDER // 2
    y = 30 + (cell // 2) * (image.shape[0] - 30) + 2 + BORDER + 18 + 40
    return image[y, x].astype(int)


def test_wrong_loops_are_framed_red_and_drawn_first(sample_frames, tmp_path):
    pairs = np.array([TRUE_PAIR, FAR_PAIR])
    path = write_montage(tmp_path / "m.png", sample_frames, pairs, np.array([True, False]), title="t")
    image = cv2.imread(str(path))
    width = image.shape[1] // 2
    assert np.abs(frame_colour(image, 0, width) - COLOURS[False]).max() <= 2  # the wrong one, first
    assert np.abs(frame_colour(image, 1, width) - COLOURS[True]).max() <= 2
    query = cv2.resize(cv2.imread(str(sample_frames[55]), cv2.IMREAD_GRAYSCALE), (image.shape[1] // 2 - 20, 120))
    assert image.std() > 20 and query.std() > 20  # real pictures, not blank cells


def test_missed_loops_are_framed_orange(sample_frames, tmp_path):
    path = write_montage(tmp_path / "m.png", sample_frames, np.array([TRUE_PAIR]), missed=True, title="missed")
    image = cv2.imread(str(path))
    assert np.abs(frame_colour(image, 0, image.shape[1]) - COLOURS["missed"]).max() <= 2


def test_pick_pairs_keeps_every_wrong_one_and_spreads_the_rest():
    correct = np.ones(100, bool)
    correct[[3, 97]] = False
    keep = pick_pairs(np.zeros((100, 2)), correct)
    assert len(keep) == MAX_PAIRS and keep[:2].tolist() == [3, 97] and keep[2] == 0 and keep[-1] == 99
    assert len(pick_pairs(np.zeros((5, 2)), None)) == 5


def test_missed_pairs_are_the_queries_without_a_correct_loop():
    truth = np.array([[60, 9], [60, 10], [60, 11], [70, 20], [80, 30]])
    det = np.array([[60, 10], [70, 45]])
    assert missed_pairs(det, np.array([True, False]), truth).tolist() == [[70, 20], [80, 30]]
    assert missed_pairs(np.zeros((0, 2), np.int64), np.zeros(0, bool), truth).tolist() == [[60, 10], [70, 20],
                                                                                            [80, 30]]


def test_evaluate_writes_both_montages(cli_sample_run, tmp_path):
    _, run = cli_sample_run
    report = evaluate.main(run, SAMPLE_DIR / "loops.txt", out=tmp_path)
    for name in ("loops_montage", "missed_montage"):
        image = cv2.imread(report["plots"][name])
        assert image is not None and image.shape[0] > 30, name
    assert cv2.imread(report["plots"]["loops_montage"]).shape[0] > 6 * 120  # 24 of the 50 loops, two a row
