"""Baseline global descriptors (thumbnail, bag of visual words) on real sample frames, and their registration."""

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from retrieval.baselines import BoVWDescriptor, ThumbnailDescriptor, build_vocabulary, load_vocabulary
from retrieval.descriptors import DESCRIPTORS
from retrieval.detect import SAMPLE_DIR
from retrieval.detector import LoopDetector, resolve_conf

# sample frames 55 and 5 are a true revisit (retrieval/sample/loops.txt); 55 and 30 are far apart
QUERY, NEAR, FAR = 55, 5, 30
VOCAB_FRAMES = range(60, 100, 4)  # vocabulary frames: none of QUERY, NEAR, FAR


def frame(i):
    return SAMPLE_DIR / "image_0" / f"{i:06d}.jpg"


@pytest.fixture(scope="module")
def vocabulary(tmp_path_factory):
    out = tmp_path_factory.mktemp("vocab") / "vocab.npz"
    return build_vocabulary([frame(i) for i in VOCAB_FRAMES], out, k=32)


def test_registered_and_selectable_by_conf(vocabulary):
    assert {"cae", "thumbnail", "bovw"} <= set(DESCRIPTORS.names())
    assert resolve_conf({"descriptor": {"name": "thumbnail"}})["descriptor"]["width"] == 64
    assert resolve_conf({"descriptor": {"name": "bovw", "vocabulary": str(vocabulary)}})["descriptor"]["vocabulary"]
    with pytest.raises(ConfigError, match="vocabulary"):
        BoVWDescriptor({"name": "bovw"})
    with pytest.raises(ConfigError, match="not found"):
        BoVWDescriptor({"name": "bovw", "vocabulary": str(vocabulary) + ".missing"})


def test_thumbnail_unit_norm_zero_mean_and_near_beats_far(sample_image):
    desc = ThumbnailDescriptor({"name": "thumbnail", "width": 40, "height": 30})
    codes = {i: desc(sample_image(i)) for i in (QUERY, NEAR, FAR)}
    for c in codes.values():
        assert c.shape == (desc.dim,) == (1200,) and c.dtype == np.float32
        assert np.linalg.norm(c) == pytest.approx(1.0, abs=1e-5)
        assert abs(c.mean()) < 1e-5
    assert codes[QUERY] @ codes[NEAR] > codes[QUERY] @ codes[FAR]
    assert np.array_equal(desc(np.full((100, 200), 7, np.uint8)), np.zeros(1200, np.float32))  # flat image


def test_vocabulary_is_built_cached_and_loadable(vocabulary):
    centroids, idf = load_vocabulary(vocabulary)
    assert centroids.shape == (32, 128) and idf.shape == (32,) and np.all(idf >= 1)
    mtime = vocabulary.stat().st_mtime_ns
    assert build_vocabulary([frame(i) for i in VOCAB_FRAMES], vocabulary, k=32) == vocabulary
    assert vocabulary.stat().st_mtime_ns == mtime  # same images and settings: reused, not rebuilt


def test_vocabulary_needs_enough_descriptors(tmp_path):
    with pytest.raises(ConfigError, match="need at least"):
        build_vocabulary([frame(0)], tmp_path / "v.npz", k=100000)


def test_bovw_unit_norm_and_near_beats_far(vocabulary, sample_image, sift_features):
    desc = BoVWDescriptor({"name": "bovw", "vocabulary": str(vocabulary)})
    assert desc.needs_features and desc.dim == 32 and desc.identity.startswith("bovw:32:")
    codes = {i: desc(sample_image(i), sift_features(i)) for i in (QUERY, NEAR, FAR)}
    for c in codes.values():
        assert c.shape == (32,) and c.dtype == np.float32
        assert np.linalg.norm(c) == pytest.approx(1.0, abs=1e-5) and np.all(c >= 0)
    assert codes[QUERY] @ codes[NEAR] > codes[QUERY] @ codes[FAR]
    # without features it extracts SIFT itself (same defaults as the detector)
    np.testing.assert_allclose(desc(sample_image(QUERY)), codes[QUERY], atol=1e-6)


def test_detector_runs_with_baselines(vocabulary, sample_image, sample_K):
    for enc in ({"name": "thumbnail"}, {"name": "bovw", "vocabulary": str(vocabulary)}):
        conf = {"descriptor": enc, "search": {"exclude_recent": 1}, "calibration": {"online": False}}  # 2 frames:
        with LoopDetector(conf, K=sample_K) as det:  # the fixed policy (a stream this short cannot calibrate)
            det.process(sample_image(NEAR), 0)
            res = det.process(sample_image(QUERY), 1)
        assert [c.frame_id for c in res.candidates] == [0]
        assert res.loop is not None and res.loop.frame_id == 0
