import re
import socket

import cv2
import numpy as np
import pytest
import torch

import cae
from cae_lcd.core.conf import ConfigError
from cae.model import ConvAutoencoder, Encoder
from cae.encode import encode_images
from cae.preprocess import preprocess, to_network_u8
from cae.weights import (DEFAULT_WEIGHTS, encoder_identity, load_autoencoder, load_checkpoint, load_encoder,
                         save_checkpoint)


@pytest.fixture(scope="module")
def frames(sample_image):
    return preprocess([sample_image(0), sample_image(70)])


class TestLoadEncoder:
    def test_shipped_weights_without_network(self, monkeypatch):
        def no_network(*args, **kwargs):
            raise AssertionError("load_encoder tried to use the network")

        monkeypatch.setattr(socket.socket, "connect", no_network)
        monkeypatch.setattr(socket, "create_connection", no_network)
        assert DEFAULT_WEIGHTS.is_file()
        enc = load_encoder(device="cpu")
        assert isinstance(enc, Encoder)
        assert not enc.training
        assert re.fullmatch(r"[0-9a-f]{16}", enc.identity)
        assert enc.features[0].weight.is_contiguous(memory_format=torch.channels_last)

    def test_identity_stable_and_weight_dependent(self, encoder):
        again = load_encoder(device="cpu")
        assert again.identity == encoder.identity == encoder_identity(again)
        torch.manual_seed(0)
        assert encoder_identity(Encoder()) != encoder.identity

    def test_shipped_weights_differ_from_init(self, encoder):
        # trained weights are no longer N(0, 0.05) with zero biases
        assert any(torch.count_nonzero(m.bias) > 0 for m in encoder.modules() if isinstance(m, torch.nn.Conv2d))

    def test_encoder_only_checkpoint_round_trip(self, tmp_path, encoder, frames):
        path = tmp_path / "enc.pt"
        save_checkpoint(path, encoder, {"note": "encoder only"})
        ckpt = load_checkpoint(path)
        assert set(ckpt) >= {"format_version", "conf", "state_dict"}
        assert ckpt["conf"] == {"note": "encoder only", "input_norm": encoder.input_norm,  # the encoder's own
                                "lowpass": encoder.lowpass}
        enc2 = load_encoder(path, device="cpu")
        assert enc2.identity == encoder.identity
        with torch.no_grad():
            torch.testing.assert_close(enc2(frames), encoder(frames))

    def test_full_autoencoder_checkpoint(self, tmp_path, frames):
        torch.manual_seed(3)
        ae = ConvAutoencoder().eval()
        path = tmp_path / "ae.pt"
        save_checkpoint(path, ae, {})
        enc = load_encoder(path, device="cpu")
        assert enc.identity == encoder_identity(ae.encoder)
        with torch.no_grad():
            torch.testing.assert_close(enc(frames), ae.encoder(frames).reshape(2, -1), rtol=1e-5, atol=1e-5)

    def test_missing_path(self, tmp_path):
        with pytest.raises(ConfigError, match="not found"):
            load_encoder(tmp_path / "missing.pt")

    def test_garbage_file(self, tmp_path):
        bad = tmp_path / "garbage.pt"
        bad.write_bytes(b"this is not a torch checkpoint" * 50)
        with pytest.raises(ConfigError, match="garbage.pt"):
            load_encoder(bad)

    def test_wrong_keys(self, tmp_path):
        path = tmp_path / "wrong.pt"
        torch.save({"conf": {}, "state_dict": {"foo.weight": torch.zeros(3)}}, path)
        with pytest.raises(ConfigError, match="do not fit"):
            load_encoder(path)

    def test_wrong_shapes(self, tmp_path, encoder):
        state = {k: v.clone() for k, v in encoder.state_dict().items()}
        state["features.0.weight"] = torch.zeros(32, 3, 5, 5)
        path = tmp_path / "shapes.pt"
        torch.save({"conf": {}, "state_dict": state}, path)
        with pytest.raises(ConfigError):
            load_encoder(path)

    def test_extra_key_rejected_strict(self, tmp_path, encoder):
        state = dict(encoder.state_dict())
        state["features.99.weight"] = torch.zeros(1)
        path = tmp_path / "extra.pt"
        torch.save({"conf": {}, "state_dict": state}, path)
        with pytest.raises(ConfigError):
            load_encoder(path)

    def test_not_a_checkpoint(self, tmp_path):
        path = tmp_path / "plain.pt"
        torch.save({"weights": torch.zeros(2)}, path)
        with pytest.raises(ConfigError, match="state_dict"):
            load_encoder(path)


class TestLoadAutoencoder:
    def test_shipped(self, encoder, frames):
        ae = load_autoencoder(device="cpu")
        assert isinstance(ae, ConvAutoencoder) and not ae.training
        assert encoder_identity(ae.encoder) == encoder.identity
        rec = ae.reconstruct(frames)
        assert rec.shape == (2, 3, 256, 256)

    def test_encoder_only_checkpoint_does_not_fit(self, tmp_path, encoder):
        path = tmp_path / "enc.pt"
        save_checkpoint(path, encoder, {})
        with pytest.raises(ConfigError):
            load_autoencoder(path)


class TestPackageApi:
    def test_exports(self):
        assert cae.CODE_DIM == 4096 and cae.INPUT_SIZE == 256
        for name in cae.__all__:
            assert hasattr(cae, name)


class TestInputNormAndStillCos:
    """What a checkpoint says about reading its input (``input_norm``) and about a still camera (``still_cos``)."""

    def test_the_shipped_and_the_paper_weights_say_what_they_read(self):
        from cae.weights import RECONSTRUCTION_WEIGHTS, STILL_COS

        shipped, paper = load_encoder(device="cpu"), load_encoder(RECONSTRUCTION_WEIGHTS, device="cpu")
        assert (shipped.input_norm, paper.input_norm) == ("standardise", "none")  # paper: a conf without the key
        assert shipped.still_cos < paper.still_cos == STILL_COS

    def test_equal_weights_read_otherwise_are_another_identity(self, encoder):
        other = Encoder("none")
        other.load_state_dict(encoder.state_dict())
        assert encoder_identity(other) != encoder_identity(encoder)
        blurred = Encoder(encoder.input_norm, encoder.lowpass + 0.5)
        blurred.load_state_dict(encoder.state_dict())
        assert encoder_identity(blurred) != encoder_identity(encoder)

    def test_the_low_pass_is_the_checkpoints(self, tmp_path, encoder, sample_image):
        """``lowpass`` comes from the checkpoint's conf (0 without one) and reaches every encoding of a small image."""
        from cae.weights import RECONSTRUCTION_WEIGHTS

        assert load_encoder(RECONSTRUCTION_WEIGHTS, device="cpu").lowpass == 0.0
        path = tmp_path / "lp.pt"
        torch.save({"format_version": 1, "conf": {"input_norm": encoder.input_norm, "lowpass": 1.5},
                    "state_dict": encoder.state_dict()}, path)
        blurred, plain = load_encoder(path, device="cpu"), load_encoder(path, device="cpu")
        plain.lowpass = 0.0
        assert blurred.lowpass == 1.5
        small = cv2.resize(sample_image(10), (64, 32), interpolation=cv2.INTER_AREA)
        want = encode_images(blurred, [to_network_u8(small, lowpass=1.5)], prepared=True)
        np.testing.assert_array_equal(encode_images(blurred, [small]), want)
        assert not np.array_equal(encode_images(blurred, [small]), encode_images(plain, [small]))

    @pytest.mark.parametrize("conf, match", [({"input_norm": "clahe"}, "input_norm must be one of"),
                                             ({"still_cos": 1.5}, r"still_cos must be a number in \[0.9, 1\)"),
                                             ({"lowpass": -1}, r"lowpass must be a number in \[0, 3\]"),
                                             ({"lowpass": "yes"}, r"lowpass must be a number in \[0, 3\]")])
    def test_a_bad_value_is_named(self, tmp_path, encoder, conf, match):
        path = tmp_path / "bad.pt"
        torch.save({"format_version": 1, "conf": conf, "state_dict": encoder.state_dict()}, path)
        with pytest.raises(ConfigError, match=match):
            load_encoder(path, device="cpu")
