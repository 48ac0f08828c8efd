import cv2
import numpy as np
import pytest

from core.conf import ConfigError
from core.errors import ImageError
from verify.gate import EdgeGate, GateResult


class TestEdgeGate:
    @pytest.mark.parametrize("seq,frames", [("00", range(0, 200, 40)), ("07", range(0, 160, 40)),
                                            ("90", range(0, 200, 50))])
    def test_real_kitti_frames_pass(self, kitti_image, seq, frames):
        gate = EdgeGate()
        for i in frames:
            res = gate(kitti_image(seq, i))
            assert isinstance(res, GateResult)
            assert res.passed, (seq, i, res.edge_ratio)
            assert 0.04 <= res.edge_ratio <= 0.5

    def test_all_sample_frames_pass(self, sample_image):
        gate = EdgeGate()
        ratios = [gate(sample_image(i)).edge_ratio for i in range(0, 100, 9)]
        assert min(ratios) >= 0.04

    def test_uniform_grey_rejected(self):
        res = EdgeGate()(np.full((376, 1241), 128, np.uint8))
        assert not res.passed
        assert res.edge_ratio == 0.0

    def test_blurred_frame_rejected(self, sample_image):
        img = sample_image(10)
        gate = EdgeGate()
        assert gate(img).passed
        res = gate(cv2.GaussianBlur(img, (0, 0), 8))
        assert not res.passed
        assert res.edge_ratio < 0.01

    def test_edge_ratio_matches_reference(self, sample_image):
        img = sample_image(20)
        small = cv2.resize(img, (256, 256), interpolation=cv2.INTER_LINEAR)  # 620x188: y grows -> bilinear
        ref = np.count_nonzero(cv2.Canny(small, 100, 200)) / 256 ** 2
        assert EdgeGate().edge_ratio(img) == pytest.approx(ref)

    def test_formats_equal(self, sample_image):
        img = sample_image(30)
        gate = EdgeGate()
        r = gate(img).edge_ratio
        assert gate(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)).edge_ratio == r
        assert gate(img.astype(np.uint16) * 257).edge_ratio == r

    def test_threshold_and_disabled(self, sample_image):
        img = sample_image(30)
        ratio = EdgeGate().edge_ratio(img)
        assert not EdgeGate({"min_edge_ratio": ratio + 1e-6})(img).passed
        assert EdgeGate({"min_edge_ratio": ratio})(img).passed
        grey = np.full((100, 100), 7, np.uint8)
        res = EdgeGate({"enabled": False})(grey)
        assert res.passed and res.edge_ratio == 0.0

    def test_bad_conf_and_image(self):
        with pytest.raises(ConfigError, match="gate.min_ratio"):
            EdgeGate({"min_ratio": 0.1})
        with pytest.raises(ImageError):
            EdgeGate()(np.zeros((5, 5), np.uint8))
