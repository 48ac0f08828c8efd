import cv2
import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from verify.features import FEATURES, SIFT, Features, create_extractor


def _check(f: Features, n=None):
    assert f.keypoints.dtype == np.float32 and f.keypoints.ndim == 2 and f.keypoints.shape[1] == 2
    assert f.descriptors.dtype == np.float32 and f.descriptors.shape == (len(f), 128)
    assert f.scales.dtype == np.float32 and f.scales.shape == (len(f),)
    if n is not None:
        assert len(f) == n


class TestFeatures:
    def test_empty(self):
        f = Features.empty()
        _check(f, 0)
        assert f.keypoints.shape == (0, 2) and f.descriptors.shape == (0, 128)
        b = Features.empty(32, np.uint8)
        assert b.descriptors.shape == (0, 32) and b.descriptors.dtype == np.uint8


class TestFeaturesCompact:
    def test_sift_descriptors_become_uint8_exactly(self, sift_features):
        f = sift_features(10)
        c = f.compact()
        assert f.descriptors.dtype == np.float32 and c.descriptors.dtype == np.uint8
        np.testing.assert_array_equal(c.descriptors.astype(np.float32), f.descriptors)
        assert len(c) == len(f)
        np.testing.assert_allclose(c.keypoints, f.keypoints, atol=1 / 16)  # kept in 1/8 pixel
        np.testing.assert_array_equal(c.keypoints * 8, np.round(c.keypoints * 8))
        np.testing.assert_allclose(c.scales, f.scales, rtol=1e-3)  # float16 precision
        again = c.compact()  # idempotent: what the store reads back compacts to itself
        np.testing.assert_array_equal(again.keypoints, c.keypoints)
        np.testing.assert_array_equal(again.scales, c.scales)

    def test_non_integer_descriptors_unchanged(self, sample_image):
        f = SIFT({"root_sift": True}).extract(sample_image(10))
        assert f.compact().descriptors is f.descriptors

    def test_empty(self):
        assert Features.empty().compact().descriptors.shape == (0, 128)


@pytest.fixture(scope="module")
def kitti_full(kitti_image):
    return kitti_image("00", 10)  # (376, 1241)


class TestSIFT:
    def test_keypoints_in_original_pixels(self, kitti_full):
        assert kitti_full.shape == (376, 1241)
        f = SIFT({"resize_max": 640, "max_features": 1000}).extract(kitti_full)
        _check(f)
        assert len(f) > 500
        x, y = f.keypoints[:, 0], f.keypoints[:, 1]
        assert x.max() > 1100 and y.max() > 330  # original scale, not the 640-wide working image
        assert x.min() >= 0 and x.max() <= 1241 and y.min() >= 0 and y.max() <= 376
        assert f.scales.min() > 0

    def test_resized_keypoints_agree_with_full_resolution(self, kitti_full):
        low = SIFT({"resize_max": 640, "max_features": 1000}).extract(kitti_full)
        full = SIFT({"resize_max": None, "max_features": 5000}).extract(kitti_full)
        d = np.linalg.norm(low.keypoints[:, None, :] - full.keypoints[None, :, :], axis=2).min(axis=1)
        # most keypoints found at the lower scale exist at (nearly) the same place at full resolution
        assert np.median(d) < 1.5

    def test_upscaled_image_scales_keypoints(self, sample_image):
        img = sample_image(10)  # 620x188
        up = cv2.resize(img, (1240, 376), interpolation=cv2.INTER_LINEAR)
        f_up = SIFT({"resize_max": 620, "max_features": 3000}).extract(up)
        f = SIFT({"resize_max": None, "max_features": 3000}).extract(img)
        assert f_up.keypoints[:, 0].max() > 1100  # mapped back to the 1240-wide input
        d = np.linalg.norm(f_up.keypoints[:, None, :] / 2 - f.keypoints[None, :, :], axis=2).min(axis=1)
        assert np.median(d) < 1.0

    def test_never_upscales(self, sample_image):
        img = sample_image(10)
        np.testing.assert_array_equal(SIFT({"resize_max": 640}).extract(img).keypoints,  # 620 px wide already
                                      SIFT({"resize_max": None}).extract(img).keypoints)

    @pytest.mark.parametrize("cap", [50, 300])
    def test_max_features(self, sample_image, cap):
        f = SIFT({"max_features": cap}).extract(sample_image(10))
        _check(f, cap)

    def test_formats_equal(self, sample_image, sift_features):
        img = sample_image(5)
        ref = sift_features(5)
        sift = SIFT()
        for variant in (cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), cv2.cvtColor(img, cv2.COLOR_GRAY2BGRA),
                        img.astype(np.uint16) * 257, img.astype(np.float32) / 255.0):
            f = sift.extract(variant)
            np.testing.assert_array_equal(f.keypoints, ref.keypoints)
            np.testing.assert_array_equal(f.descriptors, ref.descriptors)
        twelve = sift.extract(img.astype(np.uint16) * 16)
        _check(twelve)
        assert abs(len(twelve) - len(ref)) < 0.1 * len(ref)

    def test_descriptors_integer_valued(self, sift_features):
        d = sift_features(5).descriptors
        assert np.array_equal(d, np.round(d)) and d.min() >= 0 and d.max() <= 255

    def test_blank_image_gives_empty(self):
        f = SIFT().extract(np.full((188, 620), 90, np.uint8))
        _check(f, 0)
        assert f.keypoints.shape == (0, 2) and f.descriptors.shape == (0, 128) and f.scales.shape == (0,)

    def test_root_sift(self, sample_image):
        f = SIFT({"root_sift": True, "max_features": 200}).extract(sample_image(5))
        _check(f, 200)
        # RootSIFT: sqrt of L1-normalised descriptors (x 512): squares sum to 512^2 per row
        np.testing.assert_allclose((f.descriptors.astype(np.float64) ** 2).sum(1), 512.0 ** 2, rtol=1e-4)

    def test_unknown_option(self):
        with pytest.raises(ConfigError, match="features.nfeatures"):
            SIFT({"nfeatures": 10})


class TestCreateExtractor:
    def test_by_name(self):
        assert isinstance(create_extractor(), SIFT)
        ext = create_extractor({"name": "sift", "max_features": 10})
        assert isinstance(ext, SIFT) and ext.conf["max_features"] == 10
        assert "sift" in FEATURES.names()
        with pytest.raises(ConfigError, match="unknown feature extractor 'surf'"):
            create_extractor({"name": "surf"})

    @pytest.mark.parametrize("name", ["sift", "orb"])
    def test_a_cap_beyond_a_c_int_is_a_config_error(self, name):
        """OpenCV takes the cap as a C int: 10**12 was an internal error from ``SIFT_create``, not a conf error."""
        with pytest.raises(ConfigError, match="'features.max_features' must be an integer >= 1 and <= 100000"):
            create_extractor({"name": name, "max_features": 10**12})
        assert create_extractor({"name": name, "max_features": 100_000}).conf["max_features"] == 100_000


class TestORB:
    def test_binary_hamming_features(self, sample_image):
        from verify.features import ORB, create_extractor
        f = create_extractor({"name": "orb"}).extract(sample_image(5))
        assert isinstance(create_extractor({"name": "orb"}), ORB)
        assert 100 < len(f) <= 800 and f.descriptors.shape == (len(f), 32) and f.descriptors.dtype == np.uint8
        assert f.metric == "hamming"

    def test_empty_image_right_shapes(self):
        from verify.features import ORB
        f = ORB().extract(np.full((64, 64), 128, np.uint8))
        assert f.keypoints.shape == (0, 2) and f.descriptors.shape == (0, 32) and f.metric == "hamming"
