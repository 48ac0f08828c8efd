import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cae.model import CODE_DIM, CODE_SHAPE, INPUT_SIZE, ConvAutoencoder, Decoder, Encoder, MaxPool2x2
from cae.preprocess import preprocess


@pytest.fixture(scope="module")
def batch(sample_image):
    """Three real sample frames as the network input ``(3, 3, 256, 256)``."""
    return preprocess([sample_image(i) for i in (0, 20, 60)])


class TestEncoder:
    def test_output_shape(self, batch):
        torch.manual_seed(0)
        enc = Encoder().eval()
        with torch.no_grad():
            out = enc(batch)
            fmap = enc.forward_map(batch)
        assert out.shape == (3, CODE_DIM) == (3, 4096)
        assert fmap.shape == (3, *CODE_SHAPE)
        # the flat code is the channel-major (C, H, W) flattening of the map, of unit norm (as encode_images')
        torch.testing.assert_close(out, F.normalize(fmap.reshape(3, -1), dim=1))
        torch.testing.assert_close(out.norm(dim=1), torch.ones(3))

    def test_codes_are_those_of_encode_images(self, encoder, batch, sample_image):
        from cae import encode_images

        with torch.no_grad():
            out = encoder(batch).numpy()
        np.testing.assert_allclose(out, encode_images(encoder, [sample_image(i) for i in (0, 20, 60)]), atol=1e-6)

    @pytest.mark.parametrize("shape", [(1, 3, 224, 224), (1, 1, 256, 256), (3, 256, 256), (1, 3, 256, 128)])
    def test_other_input_shapes_refused(self, shape):
        from cae_lcd.core.errors import ImageError

        with pytest.raises(ImageError, match=r"the encoder takes \(B, 3, 256, 256\) images; got"):
            Encoder()(torch.zeros(shape))

    def test_deterministic(self, encoder, batch):
        with torch.no_grad():
            a = encoder(batch)
            b = encoder(batch)
        assert torch.equal(a, b)

    def test_channels_last_equals_contiguous(self, encoder, batch):
        x_cl = batch.contiguous(memory_format=torch.channels_last)
        x_c = batch.contiguous()
        assert x_cl.is_contiguous(memory_format=torch.channels_last) and x_c.is_contiguous()
        with torch.no_grad():
            a = encoder(x_cl)
            b = encoder(x_c)
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
        assert a.abs().max() > 0  # real features, not all-zero ReLU outputs

    def test_each_block_is_the_papers_conv_relu_pool(self, encoder, batch):
        """The blocks pool before their ReLU (the ReLU on a quarter of the values: BENCHMARKS.md); max and ReLU
        commute, so the code is the paper's conv -> ReLU -> max-pool bit for bit."""
        convs = [m for m in encoder.features if isinstance(m, torch.nn.Conv2d)]
        assert len(convs) == len(Encoder.filters)
        with torch.no_grad():
            h = encoder.network_input(batch)
            for conv in convs:
                h = F.max_pool2d(F.relu(F.conv2d(h, conv.weight, conv.bias, padding=1)), 2)
            assert torch.equal(encoder.forward_map(batch), h)

    def test_batch_independent(self, encoder, batch):
        with torch.no_grad():
            full = encoder(batch)
            single = torch.cat([encoder(batch[i:i + 1]) for i in range(len(batch))])
        torch.testing.assert_close(full, single, rtol=1e-5, atol=1e-5)

    def test_init_distribution(self):
        torch.manual_seed(0)
        enc = Encoder()
        convs = [m for m in enc.modules() if isinstance(m, torch.nn.Conv2d)]
        assert [c.out_channels for c in convs] == [32, 32, 32, 16]
        assert all(c.kernel_size == (3, 3) and c.padding == (1, 1) for c in convs)
        w = torch.cat([c.weight.detach().ravel() for c in convs])
        assert abs(w.std().item() - 0.05) < 0.003
        assert abs(w.mean().item()) < 0.003
        assert all(torch.count_nonzero(c.bias) == 0 for c in convs)


class TestMaxPool2x2:
    @pytest.fixture(scope="class")
    def maps(self, encoder, batch):
        """The first block's conv output on real frames, channels-last ``(3, 32, 256, 256)``, one value NaN."""
        with torch.no_grad():
            x = encoder.features[0](encoder.network_input(batch)).contiguous(memory_format=torch.channels_last)
        x[1, 5, 17, 40] = float("nan")
        return x

    def test_the_values_of_max_pool2d(self, maps):
        with torch.inference_mode():
            got = MaxPool2x2()(maps)
        want = F.max_pool2d(maps, 2)
        assert got.shape == want.shape == (3, 32, 128, 128)
        assert torch.equal(got.nan_to_num(-7.0), want.nan_to_num(-7.0))  # bit for bit, the NaN where it was
        assert torch.isnan(got[1, 5, 8, 20])
        assert got.is_contiguous(memory_format=torch.channels_last)  # what the next conv reads fastest

    @pytest.mark.parametrize("shape", [(1, 4, 7, 6), (1, 4, 6, 7), (2, 3, 5, 5)])
    def test_odd_sides_pool_as_max_pool2d(self, shape):
        x = torch.randn(shape).contiguous(memory_format=torch.channels_last)
        with torch.inference_mode():
            assert torch.equal(MaxPool2x2()(x), F.max_pool2d(x, 2))

    def test_gradient_is_max_pool2d_s(self, maps):
        x = maps[:1].nan_to_num(0.0).clone().requires_grad_(True)
        MaxPool2x2()(x).sum().backward()
        y = x.detach().clone().requires_grad_(True)
        F.max_pool2d(y, 2).sum().backward()
        assert torch.equal(x.grad, y.grad)  # training is unchanged: one input of each window gets the gradient


class TestDecoder:
    def test_output_shape(self):
        torch.manual_seed(0)
        dec = Decoder().eval()
        with torch.no_grad():
            out = dec(torch.rand(2, *CODE_SHAPE))
        assert out.shape == (2, 3, INPUT_SIZE, INPUT_SIZE)

    def test_init_distribution(self):
        torch.manual_seed(1)
        convs = [m for m in Decoder().modules() if isinstance(m, torch.nn.Conv2d)]
        assert [c.out_channels for c in convs] == [32, 32, 32, 32, 3]
        w = torch.cat([c.weight.detach().ravel() for c in convs])
        assert abs(w.std().item() - 0.05) < 0.003
        assert all(torch.count_nonzero(c.bias) == 0 for c in convs)


class TestConvAutoencoder:
    def test_output_shape(self, batch):
        torch.manual_seed(0)
        model = ConvAutoencoder().eval()
        with torch.no_grad():
            logits = model(batch)
        rec = model.reconstruct(batch)
        assert logits.shape == rec.shape == (3, 3, 256, 256)
        assert rec.min() >= 0 and rec.max() <= 1
        torch.testing.assert_close(rec, torch.sigmoid(logits))

    def test_shipped_weights_reconstruct_better_than_init(self, batch):
        import cae

        trained = cae.load_autoencoder(device="cpu")
        torch.manual_seed(0)
        fresh = ConvAutoencoder().eval()
        with torch.no_grad():
            loss_trained = F.binary_cross_entropy_with_logits(trained(batch), batch).item()
            loss_fresh = F.binary_cross_entropy_with_logits(fresh(batch), batch).item()
        # untrained logits ~0 give ~ln 2; the shipped weights must do clearly better on real frames
        assert loss_fresh == pytest.approx(np.log(2), abs=0.01)
        # measured: ~0.652 vs ~0.693 (the pixel entropy is the floor of this loss, not 0)
        assert loss_trained < loss_fresh - 0.02
        mse_trained = ((trained.reconstruct(batch) - batch) ** 2).mean()
        mse_fresh = ((fresh.reconstruct(batch) - batch) ** 2).mean()
        assert mse_trained < mse_fresh


class TestStandardisedInput:
    """``input_norm: standardise`` (the shipped weights'): each image to mean 0.5 and spread 0.25 before the first
    layer, so the light level of a frame does not reach the code."""

    def test_an_image_and_its_darkened_copy_enter_alike(self, batch):
        from cae.model import standardise

        dark = batch * 0.3  # the same frames with 30 % of the light
        torch.testing.assert_close(standardise(dark), standardise(batch), atol=2e-3, rtol=0)
        x = standardise(batch)
        assert x.min() >= 0 and x.max() <= 1
        torch.testing.assert_close(x.mean(dim=(1, 2, 3)), torch.full((3,), 0.5), atol=0.03, rtol=0)  # clipped tails
        assert standardise(batch[:0]).shape == (0, 3, INPUT_SIZE, INPUT_SIZE)  # empty in, empty out
        torch.testing.assert_close(standardise(torch.full((1, 3, 8, 8), 0.2)), torch.full((1, 3, 8, 8), 0.5), atol=1e-4,
                                   rtol=0)  # a flat image: flat grey

    def test_the_shipped_code_of_a_darkened_frame_is_its_day_code(self, encoder, sample_image):
        """On a real frame brought to 30 % of its light (uint8, as a camera gives it): the shipped weights' code
        hardly moves; the paper's raw input (the same weights, ``input_norm`` none) moves it."""
        from cae import encode_images

        day = sample_image(10)
        night = (day.astype(np.float32) * 0.3).round().astype(np.uint8)
        assert encoder.input_norm == "standardise"
        a, b = encode_images(encoder, [day, night])
        raw = Encoder("none").eval()
        raw.load_state_dict(encoder.state_dict())
        c, d = encode_images(raw.to(memory_format=torch.channels_last), [day, night])
        assert float(a @ b) > 0.99 > float(c @ d)

    def test_an_unknown_input_norm_is_refused(self):
        from cae_lcd.core.errors import ConfigError

        with pytest.raises(ConfigError, match="input_norm must be one of none, standardise"):
            Encoder("clahe")
