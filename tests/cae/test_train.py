"""Training on a handful of real sample frames, a couple of epochs: the loss must go down and resume must continue."""

import json

import numpy as np
import pytest

import cae
from cae.conf import ConfigError
from cae.train import list_images, load_image_folder, main
from cae.weights import load_checkpoint

SMALL = {"batch_size": 4, "device": "cpu", "seed": 0}


@pytest.fixture(scope="module")
def images12(tmp_path_factory, copy_sample_frames):
    """12 real sample frames spread over the sequence."""
    folder = tmp_path_factory.mktemp("train_images")
    copy_sample_frames(range(0, 96, 8), folder)
    return folder


@pytest.fixture(scope="module")
def trained(images12, tmp_path_factory):
    out = tmp_path_factory.mktemp("train_run")
    summary = main(images12, out, {**SMALL, "epochs": 2})
    return out, summary


class TestMain:
    def test_validation_loss_decreases(self, trained):
        out, s = trained
        assert s["epochs_run"] == 2
        assert len(s["history"]) == 3  # initial evaluation + 2 epochs
        assert s["first_val_loss"] == pytest.approx(np.log(2), abs=0.01)  # logits ~0 at init
        assert s["best_val_loss"] < s["first_val_loss"] - 1e-3
        assert s["best_epoch"] in (1, 2)
        assert s["best_val_loss"] == min(h["val_loss"] for h in s["history"])

    def test_run_folder(self, trained, images12):
        out, s = trained
        for name in ("best.pt", "last.pt", "conf.yaml", "split.json", "summary.json", "loss.png"):
            assert (out / name).is_file(), name
        split = json.loads((out / "split.json").read_text())
        assert len(split["train"]) + len(split["val"]) == 12
        assert len(split["val"]) == round(0.3 * 12)
        assert not set(split["train"]) & set(split["val"])
        assert json.loads((out / "summary.json").read_text())["best_val_loss"] == s["best_val_loss"]

    def test_best_checkpoint_loads(self, trained, sample_image):
        out, s = trained
        ckpt = load_checkpoint(out / "best.pt")
        assert {"conf", "state_dict"} <= set(ckpt)
        assert ckpt["conf"]["epochs"] == 2 and ckpt["conf"]["batch_size"] == 4
        assert any(k.startswith("decoder.") for k in ckpt["state_dict"])  # the full autoencoder
        assert ckpt["val_loss"] == pytest.approx(s["best_val_loss"])
        enc = cae.load_encoder(out / "best.pt", device="cpu")
        assert enc.identity != cae.load_encoder(device="cpu").identity
        codes = cae.encode_images(enc, [sample_image(0), sample_image(1)])
        assert codes.shape == (2, 4096) and np.isfinite(codes).all()
        # the full autoencoder loads strictly from the same checkpoint
        ae = cae.load_autoencoder(out / "best.pt", device="cpu")
        assert isinstance(ae, cae.ConvAutoencoder)

    def test_resume_continues(self, tmp_path, copy_sample_frames):
        images = tmp_path / "images"
        copy_sample_frames([0, 30, 60, 90, 45], images)
        out = tmp_path / "run"
        s1 = main(images, out, {**SMALL, "epochs": 1})
        assert s1["epochs_run"] == 1 and len(s1["history"]) == 2
        last1 = load_checkpoint(out / "last.pt")
        assert {"state_dict", "optimizer", "history", "epoch"} <= set(last1) and len(last1["history"]) == 2
        s2 = main(images, out, {**SMALL, "epochs": 2})
        assert len(s2["history"]) == 3
        assert [h["epoch"] for h in s2["history"]] == [0, 1, 2]
        assert s2["epochs_run"] == 2
        # the first run's history is kept, not recomputed (train_loss of epoch 0 is NaN, so compare val losses)
        assert [h["val_loss"] for h in s2["history"][:2]] == [h["val_loss"] for h in s1["history"]]
        assert s2["first_val_loss"] == s1["first_val_loss"]
        assert len(load_checkpoint(out / "last.pt")["history"]) == 3
        # a finished run resumed with the same epoch budget trains no further
        s_again = main(images, out, {**SMALL, "epochs": 2})
        assert len(s_again["history"]) == 3 and s_again["epochs_run"] == 2
        # restart ignores last.pt
        s3 = main(images, out, {**SMALL, "epochs": 1}, restart=True)
        assert len(s3["history"]) == 2

    def test_missing_or_empty_folder(self, tmp_path):
        with pytest.raises(ConfigError, match="not found"):
            main(tmp_path / "missing", tmp_path / "out", {**SMALL, "epochs": 1})
        (tmp_path / "empty").mkdir()
        (tmp_path / "empty" / "notes.txt").write_text("no images here")
        with pytest.raises(ConfigError, match="no images"):
            main(tmp_path / "empty", tmp_path / "out", {**SMALL, "epochs": 1})

    def test_unknown_conf_key(self, images12, tmp_path):
        with pytest.raises(ConfigError, match="epoch"):
            main(images12, tmp_path / "out", {"epoch": 1})

    def test_single_image_cannot_split(self, tmp_path, copy_sample_frames):
        copy_sample_frames([0], tmp_path / "one")
        with pytest.raises(ConfigError, match="at least 2"):
            main(tmp_path / "one", tmp_path / "out", {**SMALL, "epochs": 1})


class TestListImages:
    def test_recursive_sorted(self, tmp_path, copy_sample_frames):
        copy_sample_frames([0, 1], tmp_path / "b")
        copy_sample_frames([2], tmp_path / "a" / "deeper")
        (tmp_path / "readme.txt").write_text("x")
        files = list_images(tmp_path)
        assert [f.relative_to(tmp_path).as_posix() for f in files] == \
            ["a/deeper/000000.jpg", "b/000000.jpg", "b/000001.jpg"]


class TestLoadImageFolder:
    def test_skips_unreadable(self, tmp_path, copy_sample_frames, caplog):
        files = copy_sample_frames([0, 1], tmp_path)
        bad = tmp_path / "bad.png"
        bad.write_bytes(b"garbage" * 20)
        data, used = load_image_folder([files[0], bad, files[1]])
        assert data.shape == (2, 256, 256, 3) and data.dtype == np.uint8
        assert used == [files[0], files[1]]
        assert "bad.png" in caplog.text
        with pytest.raises(ConfigError):
            load_image_folder([bad])
