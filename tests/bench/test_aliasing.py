"""bench.aliasing: the issue-17 table shows the calibration's own share of the run beside its share with the run's
work it does ahead (``summary.json`` ``seconds``)."""

from __future__ import annotations

from bench.aliasing import aliasing_table


def test_calibration_share_own_and_with_the_runs_work():
    res = {"KITTI 90": {"frames": 200, "loops": 100, "precision": 1.0, "recall": 0.8, "ms": 15.5, "path": "inliers",
                        "wall_s": 10.0, "calibration_s": 5.0, "calibration_own_s": 1.2, "r10": 0.9},
           "a run with the calibration given": {"frames": 200, "loops": 0, "precision": 1.0, "recall": None,
                                                "ms": None, "path": "none", "wall_s": 4.0, "calibration_s": 0.0,
                                                "calibration_own_s": None}}
    table = aliasing_table(res)
    assert "| KITTI 90 | 200 | 100 | 1.000 | 0.800 | 0.900 | 0.889 | 15.5 | 12 % / 50 % | inliers |" in table
    assert "| n/a (no revisit) | n/a | n/a | n/a | n/a | none |" in table  # blindness as a figure: issue 27
    assert "own / with the run's work" in table.splitlines()[0]


def test_dark_proxy_darkens_the_second_pass_only(tmp_path):
    """The night proxy (issues 27 and 28): KITTI 90's first pass kept at 160x120, the second made dark and noisy,
    reproducibly (the same seed gives the same pixels)."""
    import cv2
    import numpy as np
    import pytest

    from bench.aliasing import dark_proxy_folder
    from bench.augment import darken
    from retrieval.sequences import open_sequence
    from tests.conftest import KITTI_SEQUENCES

    if not (KITTI_SEQUENCES / "90").is_dir():
        pytest.skip("shared KITTI data not found")
    frames = list(open_sequence(KITTI_SEQUENCES / "90").frames)[98:102]  # two of each pass
    a = dark_proxy_folder(tmp_path / "a", frames)
    b = dark_proxy_folder(tmp_path / "b", frames)
    imgs = [cv2.imread(str(a / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED) for i in range(4)]
    assert all(im.shape == (120, 160) for im in imgs)
    assert imgs[0].mean() > 2 * imgs[2].mean()  # the second half is dark
    assert np.array_equal(imgs[3], cv2.imread(str(b / "000003.png"), cv2.IMREAD_UNCHANGED))  # seeded
    rng = np.random.default_rng(0)
    flat = np.full((50, 50), 255, np.uint8)
    assert abs(float(darken(flat, rng).mean()) - 255 * 0.38) < 2  # 0.35 * 1 ** 1.8 + 0.03


def test_the_narrower_lens_is_the_frames_centre_brought_back_up(tmp_path):
    """The training study's lens set (issue 28): the second pass at dusk, then its centre 80 % of each side brought
    back to full size; the first pass untouched."""
    import cv2
    import numpy as np
    import pytest

    from bench.aliasing import dusk_folder
    from bench.augment import narrower
    from retrieval.sequences import open_sequence
    from tests.conftest import KITTI_SEQUENCES

    if not (KITTI_SEQUENCES / "90").is_dir():
        pytest.skip("shared KITTI data not found")
    frames = list(open_sequence(KITTI_SEQUENCES / "90").frames)[98:102]
    source = cv2.imread(str(frames[0]), cv2.IMREAD_UNCHANGED)
    zoomed = narrower(source)
    assert zoomed.shape == source.shape
    # shrunk back by 0.8 it is the source's centre window (a few grey levels of resampling), not a window beside it
    h, w = source.shape
    ch, cw, y, x = round(0.8 * h), round(0.8 * w), (h - round(0.8 * h)) // 2, (w - round(0.8 * w)) // 2
    back = cv2.resize(zoomed, (cw, ch), interpolation=cv2.INTER_AREA).astype(float)
    centre = np.abs(back - source[y:y + ch, x:x + cw]).mean()
    beside = np.abs(back - source[y:y + ch, x + 8:x + 8 + cw]).mean()
    assert centre < 4 < 2 * centre < beside
    plain, lens = dusk_folder(tmp_path / "p", frames), dusk_folder(tmp_path / "l", frames, lens=0.8)
    read = lambda d, i: cv2.imread(str(d / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)  # noqa: E731
    assert np.array_equal(read(plain, 0), read(lens, 0)) and np.array_equal(read(lens, 0), source)
    assert not np.array_equal(read(plain, 3), read(lens, 3))


def test_the_darker_proxy_leaves_too_few_keypoints_to_verify(tmp_path):
    """``DARKER``: the second pass of KITTI 90 at 160x120 keeps fewer SIFT keypoints a frame than verification needs
    (``calibration.min_features``), the first pass several times more (the proxy for the held-out night walk)."""
    import numpy as np
    import pytest

    from bench.aliasing import DARKER, dark_proxy_folder
    from cae_lcd.core.images import read_image
    from retrieval.calibrate import calibrated_features
    from retrieval.detector import resolve_conf
    from retrieval.sequences import open_sequence
    from tests.conftest import KITTI_SEQUENCES
    from verify.features import create_extractor

    if not (KITTI_SEQUENCES / "90").is_dir():
        pytest.skip("shared KITTI data not found")
    frames = list(open_sequence(KITTI_SEQUENCES / "90").frames)[::10]  # 10 of each pass
    folder = dark_proxy_folder(tmp_path / "darker", frames, **DARKER)
    conf = resolve_conf({})
    extractor = create_extractor(calibrated_features(conf))
    counts = [len(extractor.extract(read_image(folder / f"{i:06d}.png"))) for i in range(len(frames))]
    day, night = np.median(counts[:10]), np.median(counts[10:])
    assert night < conf["calibration"]["min_features"] < day / 2


def test_online_rows_beside_the_offline_ones():
    """The online table (issue 27): the stream's loops, precision and recall, its retrieval Recall@10 and the recall
    over it (a stream safe by being blind shows it), beside the offline recall, their ratio,
    the ms/frame with the refits amortised and the worst frame."""
    from bench.aliasing import online_table

    offline = {"KITTI 90": {"recall": 0.99}, "KITTI 00": {"recall": None}}
    online = {"KITTI 90": {"loops": 99, "precision": 1.0, "recall": 0.891, "r10": 0.99, "ms_mean": 61.7,
                           "ms_median": 20.2, "ms_worst": 4360.6},
              "KITTI 00": {"loops": 0, "precision": 1.0, "recall": None, "ms_mean": 40.0, "ms_median": 20.0,
                           "ms_worst": 900.0}}
    table = online_table(offline, online)
    assert "| KITTI 90 | 99 | 1.000 | 0.891 | 0.990 / 0.900 | 0.990 | 0.90 | 61.7 | 20.2 | 4361 |" in table
    assert "| KITTI 00 | 0 | 1.000 | n/a (no revisit) | n/a | n/a | n/a | 40.0 | 20.0 | 900 |" in table


def test_the_paused_proxy_stands_still_where_it_says(tmp_path, monkeypatch):
    """``paused_folder``: each frame of a pause the frame it follows under new sensor noise (``PAUSE_NOISE`` grey
    levels): a stop the calibration finds (``camera_moved``), the other frames moving."""
    import cv2
    import numpy as np

    from bench.aliasing import paused_folder
    from cae.weights import load_encoder
    from retrieval.calibrate import camera_moved
    from retrieval.descriptors import create_descriptor
    from tests.conftest import SAMPLE_DIR

    monkeypatch.setattr("bench.aliasing.PAUSES", {3: 4})
    sources = sorted((SAMPLE_DIR / "image_0").glob("*.jpg"))[:8]
    folder = paused_folder(tmp_path / "p", sources, (64, 32))
    images = [cv2.imread(str(p)) for p in sorted(folder.glob("*.png"))]
    assert len(images) == 12 and all(im.shape == (32, 64, 3) for im in images)
    diff = [np.abs(images[k].astype(float) - images[3].astype(float)).mean() for k in range(3, 8)]
    assert diff[0] == 0 and all(0.3 < d < 1.5 for d in diff[1:])  # the pause: noise only
    d = create_descriptor({"name": "cae"}, encoder=load_encoder())
    moved = camera_moved(np.stack(d.encode_batch(images)), d.still_cos)
    assert (~moved).sum() >= 3 and moved[:4].all() and moved[8:].all()


def test_the_recurring_proxy_mirrors_each_stretch_after_itself(tmp_path):
    """``recurring_folder``: each stretch, then the same frames mirrored left-right (look-alikes ``len(stretch)``
    frames apart, none the same place)."""
    import cv2
    import numpy as np

    from bench.aliasing import recurring_folder
    from tests.conftest import SAMPLE_DIR

    sources = sorted((SAMPLE_DIR / "image_0").glob("*.jpg"))
    folder = recurring_folder(tmp_path / "r", [sources[:3], sources[40:43]], (64, 32))
    images = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(folder.glob("*.png"))]
    assert len(images) == 12 and all(im.shape == (32, 64) for im in images)
    for start in (0, 6):
        for k in range(3):
            np.testing.assert_array_equal(images[start + 3 + k], cv2.flip(images[start + k], 1))
    assert not np.array_equal(images[0], images[6])  # the second stretch is another place
