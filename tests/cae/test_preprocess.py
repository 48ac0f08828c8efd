import cv2
import numpy as np
import pytest
import torch

from cae.preprocess import preprocess, to_network_u8
from cae_lcd.core.errors import ImageError


@pytest.fixture(scope="module")
def grey(sample_image):
    return sample_image(10)  # (188, 620) uint8


def _check_net_input(x, batch=1):
    assert isinstance(x, torch.Tensor)
    assert x.shape == (batch, 3, 256, 256)
    assert x.dtype == torch.float32
    assert x.min() >= 0.0 and x.max() <= 1.0


class TestPreprocess:
    def test_grey_uint8(self, grey):
        x = preprocess(grey)
        _check_net_input(x)
        # grey is replicated to three channels
        assert torch.equal(x[0, 0], x[0, 1]) and torch.equal(x[0, 1], x[0, 2])
        assert x.std() > 0.05  # a real image, not a constant

    def test_channels_last_layout(self, grey):
        assert preprocess([grey, grey]).is_contiguous(memory_format=torch.channels_last)

    def test_matches_manual_reference(self, grey):
        # 620x188 -> 256x256 shrinks x but grows y: bilinear (area averaging only when both sides shrink)
        ref = cv2.resize(grey, (256, 256), interpolation=cv2.INTER_LINEAR).astype(np.float32) / 255.0
        x = preprocess(grey)
        np.testing.assert_allclose(x[0, 0].numpy(), ref, atol=1e-6)
        big = cv2.resize(grey, (1240, 376), interpolation=cv2.INTER_LINEAR)  # both sides shrink: area
        ref_big = cv2.resize(big, (256, 256), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0
        np.testing.assert_allclose(preprocess(big)[0, 0].numpy(), ref_big, atol=1e-6)

    @pytest.mark.parametrize("layout", ["bgr", "bgra", "grey_hw1", "float32", "float64", "uint16x257"])
    def test_layouts_equal_grey(self, grey, layout):
        img = {
            "bgr": lambda g: cv2.cvtColor(g, cv2.COLOR_GRAY2BGR),
            "bgra": lambda g: cv2.cvtColor(g, cv2.COLOR_GRAY2BGRA),
            "grey_hw1": lambda g: g[:, :, None],
            "float32": lambda g: g.astype(np.float32) / 255.0,
            "float64": lambda g: g.astype(np.float64) / 255.0,
            "uint16x257": lambda g: g.astype(np.uint16) * 257,
        }[layout](grey)
        x = preprocess(img)
        _check_net_input(x)
        torch.testing.assert_close(x, preprocess(grey), rtol=0, atol=1e-6)

    def test_12bit_nearly_equal_8bit(self, grey):
        img12 = grey.astype(np.uint16) * 16  # 12-bit data in 16-bit words (max <= 4080)
        assert img12.max() < 4096
        x = preprocess(img12)
        _check_net_input(x)
        diff = (x - preprocess(grey)).abs()
        assert diff.max() <= 2.0 / 255 + 1e-6
        assert diff.mean() < 0.5 / 255

    def test_real_colour_channels_kept(self, grey):
        # a BGR image with distinct channels: the network input is RGB
        bgr = np.dstack([grey, np.roll(grey, 40, axis=1), 255 - grey])
        x = preprocess(bgr)
        _check_net_input(x)
        torch.testing.assert_close(x[:, 0], preprocess(255 - grey)[:, 0], rtol=0, atol=1e-6)  # R = BGR[..., 2]
        torch.testing.assert_close(x[:, 2], preprocess(grey)[:, 0], rtol=0, atol=1e-6)  # B = BGR[..., 0]

    def test_small_image_upsampled(self, grey):
        small = cv2.resize(grey, (160, 120), interpolation=cv2.INTER_AREA)
        x = preprocess(small)
        _check_net_input(x)
        # upsampled small frame stays close to the directly downsampled full frame
        assert (x - preprocess(grey)).abs().mean() < 0.05

    def test_lowpass_blurs_only_an_image_brought_up(self, grey):
        """``lowpass``: a Gaussian in the image's own pixels, then the same resize; only where both sides grow."""
        small = cv2.resize(grey, (64, 32), interpolation=cv2.INTER_AREA)  # a Nordland-sized frame
        ref = cv2.resize(cv2.GaussianBlur(small, (0, 0), 0.6), (256, 256), interpolation=cv2.INTER_LINEAR)
        np.testing.assert_array_equal(to_network_u8(small, lowpass=0.6)[..., 0], ref)
        assert (to_network_u8(small, lowpass=0.6) != to_network_u8(small)).any()
        torch.testing.assert_close(preprocess(small, lowpass=0.6), preprocess([small], lowpass=0.6))
        np.testing.assert_array_equal(to_network_u8(grey, lowpass=0.6), to_network_u8(grey))  # 620 px: not brought up

    def test_batch_of_mixed_sizes(self, grey):
        small = cv2.resize(grey, (160, 120))
        x = preprocess([grey, small, cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)])
        _check_net_input(x, batch=3)
        torch.testing.assert_close(x[0], x[2])

    def test_empty_list(self):
        x = preprocess([])
        assert x.shape == (0, 3, 256, 256)
        assert x.dtype == torch.float32

    @pytest.mark.parametrize("shape,dtype", [
        ((188, 620, 2), np.uint8),  # two channels
        ((188, 620, 5), np.uint8),  # five channels
        ((620,), np.uint8),  # 1-D
        ((2, 188, 620, 3), np.uint8),  # 4-D batch array
        ((4, 4), np.uint8),  # too small
        ((188, 620), np.complex64),  # unsupported dtype
    ])
    def test_bad_input_raises(self, shape, dtype):
        with pytest.raises(ImageError):
            preprocess(np.zeros(shape, dtype))
