"""Training on a handful of real sample frames, one or two epochs: the loss goes down, resume restores the weights
exactly, bad input is one ``error:`` line (never a traceback, never a half-made run folder), bad images are skipped
by name."""

import json
import logging
import resource
import shutil
import struct
import subprocess
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

import cae
import cae.train as training
from cae.model import ConvAutoencoder
from cae.preprocess import to_network_u8
from cae.train import conf_rules, default_conf, list_images, load_image_folder, main
from cae.weights import load_checkpoint, save_checkpoint
from cae_lcd.core.conf import ConfigError, check_conf, load_conf_file, merge_conf
from cae_lcd.core.errors import ImageError
from cae_lcd.core.images import read_image

REPO = Path(__file__).parents[2]
SMALL = {"batch_size": 4, "device": "cpu", "seed": 0}


def cli_main(argv):
    """``cae-lcd ARGV`` in-process (imported here so that the API tests run even when another command is broken)."""
    from cae_lcd.cli.main import main as run

    return run(argv)


def write_bomb_png(path: Path, side: int = 50000) -> Path:
    """A valid 8x8 PNG whose header claims ``side x side`` pixels (IHDR patched, CRC recomputed): a few hundred
    bytes on disk, gigabytes if anything decoded it."""
    ok, buf = cv2.imencode(".png", np.full((8, 8), 128, np.uint8))
    data = bytearray(buf.tobytes())
    assert ok and data[12:16] == b"IHDR"
    data[16:24] = struct.pack(">II", side, side)
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    path.write_bytes(bytes(data))
    return path


def trajectory(summary):
    """What an uninterrupted and a resumed run must share: epochs, losses, best (not the timings)."""
    h = summary["history"]
    return ([(e["epoch"], e["val_loss"]) for e in h], [e["train_loss"] for e in h[1:]], summary["best_val_loss"],
            summary["best_epoch"], summary["epochs_run"])


def spy_first_epoch(monkeypatch) -> list[dict]:
    """Spies on ``cae.train._train_epoch``: the returned list gets the weights the first epoch starts from."""
    started_from: list[dict] = []
    train_epoch = training._train_epoch

    def spy(model, *args, **kwargs):
        if not started_from:
            started_from.append({k: v.detach().clone() for k, v in model.state_dict().items()})
        return train_epoch(model, *args, **kwargs)

    monkeypatch.setattr(training, "_train_epoch", spy)
    return started_from


def same_weights(a, b) -> bool:
    a = a if isinstance(a, dict) else load_checkpoint(a)["state_dict"]
    b = b if isinstance(b, dict) else load_checkpoint(b)["state_dict"]
    return a.keys() == b.keys() and all(torch.equal(a[k].cpu(), b[k].cpu()) for k in a)


@pytest.fixture(scope="module")
def images12(tmp_path_factory, copy_sample_frames):
    """12 real sample frames spread over the sequence."""
    folder = tmp_path_factory.mktemp("train_images")
    copy_sample_frames(range(0, 96, 8), folder)
    return folder


@pytest.fixture(scope="module")
def images5(tmp_path_factory, copy_sample_frames):
    folder = tmp_path_factory.mktemp("train_images5")
    copy_sample_frames([0, 30, 60, 90, 45], folder)
    return folder


@pytest.fixture(scope="module")
def trained(images12, tmp_path_factory):
    out = tmp_path_factory.mktemp("train_run")
    # 4 Adam steps on 8 frames: at 3e-3 the validation loss falls 0.003, three times what the test asks (at the
    # random start's 1e-3 it fell 0.001, by a hair above or below with one view more or less)
    summary = main(images12, out, {**SMALL, "epochs": 2, "lr": 3e-3})
    return out, summary


class TestConfRules:
    def test_every_key_has_a_rule_and_defaults_pass(self):
        assert set(conf_rules) == set(default_conf)
        check_conf(default_conf, conf_rules)

    def test_preset_file_is_the_defaults(self):
        user = load_conf_file(REPO / "configs" / "train.yaml")
        assert merge_conf(default_conf, user) == default_conf

    @pytest.mark.parametrize("key, value", [("epochs", 0), ("epochs", 2.5), ("batch_size", 0), ("lr", "fast"),
                                            ("lr", 0), ("val_fraction", 1.5), ("val_fraction", 0), ("seed", -1),
                                            ("patience", True), ("min_delta", -1e-3), ("device", "tpu"),
                                            ("max_images", 1), ("lr", float("nan"))])
    def test_bad_value_named_before_anything_is_written(self, images5, tmp_path, key, value):
        out = tmp_path / "out"
        with pytest.raises(ConfigError, match=f"'{key}' must be"):
            main(images5, out, {**SMALL, key: value})
        assert not out.exists()


class TestMain:
    def test_validation_loss_decreases(self, trained):
        out, s = trained
        assert s["epochs_run"] == 2
        assert len(s["history"]) == 3  # initial evaluation + 2 epochs
        assert s["first_val_loss"] > np.log(2) - 0.01  # reconstruction (logits ~0 at init: log 2) + place term
        assert s["best_val_loss"] < s["first_val_loss"] - 1e-3
        assert s["best_epoch"] in (1, 2)
        assert s["best_val_loss"] == min(h["val_loss"] for h in s["history"])
        assert s["images"] == 12 and s["unreadable"] == 0 and s["skipped"] == []

    def test_run_folder(self, trained):
        out, s = trained
        for name in ("best.pt", "last.pt", "conf.yaml", "split.json", "summary.json", "loss.png"):
            assert (out / name).is_file(), name
        assert not [p.name for p in out.iterdir() if p.name.startswith(".") or p.suffix == ".tmp"]  # no temp files
        split = json.loads((out / "split.json").read_text())
        assert len(split["train"]) + len(split["val"]) == 12
        assert len(split["val"]) == round(0.3 * 12)
        assert not set(split["train"]) & set(split["val"])
        assert json.loads((out / "summary.json").read_text())["best_val_loss"] == s["best_val_loss"]
        assert yaml.safe_load((out / "conf.yaml").read_text())["epochs"] == 2

    def test_best_checkpoint_loads(self, trained, sample_image):
        out, s = trained
        assert Path(s["best"]) == out / "best.pt"
        ckpt = load_checkpoint(out / "best.pt")
        assert {"conf", "state_dict"} <= set(ckpt)
        assert ckpt["conf"]["epochs"] == 2 and ckpt["conf"]["batch_size"] == 4
        assert any(k.startswith("decoder.") for k in ckpt["state_dict"])  # the full autoencoder
        assert ckpt["val_loss"] == pytest.approx(s["best_val_loss"])
        enc = cae.load_encoder(out / "best.pt", device="cpu")
        assert enc.identity != cae.load_encoder(device="cpu").identity
        codes = cae.encode_images(enc, [sample_image(0), sample_image(1)])
        assert codes.shape == (2, 4096) and np.isfinite(codes).all()
        assert isinstance(cae.load_autoencoder(out / "best.pt", device="cpu"), cae.ConvAutoencoder)
        # the code normalisation fitted on the training images travels with the weights
        assert enc.whitening is not None and enc.whitening.dim == 3  # 12 images: a quarter of them
        assert s["whitening"] == {"dim": 3, "fitted_on": 12}

    def test_max_images_subset(self, images12, tmp_path):
        s = main(images12, tmp_path / "run", {**SMALL, "epochs": 1, "max_images": 4})
        split = json.loads((tmp_path / "run" / "split.json").read_text())
        assert s["images"] == 4 and len(split["train"]) + len(split["val"]) == 4

    def test_missing_or_empty_folder(self, tmp_path):
        with pytest.raises(ConfigError, match="not found"):
            main(tmp_path / "missing", tmp_path / "out", {**SMALL, "epochs": 1})
        (tmp_path / "empty").mkdir()
        (tmp_path / "empty" / "notes.txt").write_text("no images here")
        with pytest.raises(ConfigError, match="no images"):
            main(tmp_path / "empty", tmp_path / "out", {**SMALL, "epochs": 1})
        assert not (tmp_path / "out").exists()

    def test_unknown_conf_key(self, images12, tmp_path):
        with pytest.raises(ConfigError, match="'epoch'"):
            main(images12, tmp_path / "out", {"epoch": 1})
        assert not (tmp_path / "out").exists()

    def test_single_image_cannot_split(self, tmp_path, copy_sample_frames):
        copy_sample_frames([0], tmp_path / "one")
        with pytest.raises(ConfigError, match="at least 2"):
            main(tmp_path / "one", tmp_path / "out", {**SMALL, "epochs": 1})
        assert not (tmp_path / "out").exists()

    def test_diverged_training_is_an_error(self, images5, tmp_path, monkeypatch):
        monkeypatch.setattr(training, "_evaluate", lambda *a: float("nan"))
        with pytest.raises(ConfigError, match="diverged.*'lr'"):
            main(images5, tmp_path / "out", {**SMALL, "epochs": 1})
        assert not (tmp_path / "out" / "best.pt").exists() and not (tmp_path / "out" / "last.pt").exists()


RESUME = {**SMALL, "batch_size": 2}  # 3 training images in 2 batches: the batch order matters too


@pytest.fixture(scope="module")
def straight(images5, tmp_path_factory):
    """2 uninterrupted epochs."""
    out = tmp_path_factory.mktemp("straight")
    return out, main(images5, out, {**RESUME, "epochs": 2})


@pytest.fixture(scope="module")
def after_one(images5, tmp_path_factory):
    """A run folder after 1 epoch of 2 (copied by each test before resuming)."""
    out = tmp_path_factory.mktemp("after_one")
    return out, main(images5, out, {**RESUME, "epochs": 1})


class TestResume:
    """Resume must restore the weights, the optimizer and the batch order: 1 epoch + 1 resumed epoch == 2
    uninterrupted epochs, bit for bit, and leaving out the weights or the optimizer breaks that equality (so the
    check can fail)."""

    @staticmethod
    def resume(images5, after_one, tmp_path, monkeypatch):
        """Copies the 1-epoch run, resumes it to 2 epochs; returns the summary and the weights trained from."""
        out = tmp_path / "run"
        shutil.copytree(after_one[0], out)
        started_from = spy_first_epoch(monkeypatch)
        return out, main(images5, out, {**RESUME, "epochs": 2}), started_from[0]

    def test_resumed_run_equals_uninterrupted_run(self, images5, after_one, straight, tmp_path, monkeypatch):
        s1 = after_one[1]
        last1 = load_checkpoint(after_one[0] / "last.pt")
        assert {"state_dict", "optimizer", "history", "epoch"} <= set(last1) and last1["epoch"] == 1
        out, s2, started_from = self.resume(images5, after_one, tmp_path, monkeypatch)
        assert same_weights(started_from, last1["state_dict"])  # epoch 2 trained from the saved epoch-1 weights
        assert [h["epoch"] for h in s2["history"]] == [0, 1, 2]
        assert [h["val_loss"] for h in s2["history"][:2]] == [h["val_loss"] for h in s1["history"]]  # kept
        assert trajectory(s2) == trajectory(straight[1])
        assert same_weights(out / "last.pt", straight[0] / "last.pt")
        assert same_weights(out / "best.pt", straight[0] / "best.pt")

    @pytest.mark.parametrize("skipped", [ConvAutoencoder, torch.optim.Adam], ids=["weights", "optimizer"])
    def test_not_restoring_is_detected(self, images5, after_one, straight, tmp_path, monkeypatch, skipped):
        monkeypatch.setattr(skipped, "load_state_dict", lambda self, *a, **k: None)
        out, s2, started_from = self.resume(images5, after_one, tmp_path, monkeypatch)
        assert len(s2["history"]) == 3  # it did resume (the history comes from last.pt) ...
        assert trajectory(s2) != trajectory(straight[1])  # ... but the comparison above would have failed
        assert not same_weights(out / "last.pt", straight[0] / "last.pt")
        if skipped is ConvAutoencoder:
            assert not same_weights(started_from, load_checkpoint(after_one[0] / "last.pt")["state_dict"])

    def test_an_anchored_fine_tune_resumes_bit_for_bit(self, images5, tmp_path):
        """``anchor`` (on by default where ``init`` is given) rebuilds its frozen copy of the init weights on resume:
        1 + 1 resumed epochs equal 2 uninterrupted ones; the term is in the validation loss from the start (a changed
        view's code is not its clean frame's, even where the copy is the model)."""
        conf = {**RESUME, "init": "shipped"}
        straight = main(images5, tmp_path / "straight", {**conf, "epochs": 2})
        main(images5, tmp_path / "resumed", {**conf, "epochs": 1})
        resumed = main(images5, tmp_path / "resumed", {**conf, "epochs": 2})
        assert trajectory(resumed) == trajectory(straight)
        assert same_weights(tmp_path / "resumed" / "last.pt", tmp_path / "straight" / "last.pt")
        free = main(images5, tmp_path / "free", {**conf, "anchor": 0.0, "epochs": 1})
        assert straight["history"][0]["val_loss"] > free["history"][0]["val_loss"] + 0.1

    def test_finished_run_and_restart(self, images5, straight, tmp_path):
        out = tmp_path / "run"
        shutil.copytree(straight[0], out)
        again = main(images5, out, {**RESUME, "epochs": 2})  # the same epoch budget: no further training
        assert trajectory(again) == trajectory(straight[1])
        s3 = main(images5, out, {**RESUME, "epochs": 1}, restart=True)
        assert len(s3["history"]) == 2 and len(load_checkpoint(out / "last.pt")["history"]) == 2

    @pytest.mark.parametrize("damage", ["garbage", "no_optimizer"])
    def test_damaged_last_pt_is_one_line(self, images5, tmp_path, capsys, damage):
        out = tmp_path / "run"
        out.mkdir()
        if damage == "garbage":
            (out / "last.pt").write_bytes(b"not a checkpoint" * 10)
        else:
            save_checkpoint(out / "last.pt", ConvAutoencoder(), {})  # a best.pt-like file: no optimizer state
        before = (out / "last.pt").read_bytes()
        with pytest.raises(ConfigError, match=r"last\.pt.*--restart"):
            main(images5, out, {**SMALL, "epochs": 1})
        code = cli_main(["train", "--images", str(images5), "--out", str(out), "--device", "cpu"])
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err
        errors = [line for line in err.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and "last.pt" in errors[0] and "--restart" in errors[0]
        assert (out / "last.pt").read_bytes() == before
        assert sorted(p.name for p in out.iterdir()) == ["last.pt"]  # nothing else written


@dataclass
class Bad:
    """One bad invocation of ``cae-lcd train``: what to pass, and what the error line must name."""

    args: list = field(default_factory=list)
    conf: dict | None = None  # written to a --config file
    images: str = "good"  # "good", "missing" or "empty"
    out: str = "new"  # "new" or "file"
    needle: str = ""  # must appear in the error line ({images}/{out} are filled in)
    needs_no_cuda: bool = False


BAD = {
    "epochs 0": Bad(["--epochs", "0"], needle="'epochs' must be an integer >= 1"),
    "batch_size 0": Bad(conf={"batch_size": 0}, needle="'batch_size' must be an integer >= 1"),
    "lr fast": Bad(conf={"lr": "fast"}, needle="'lr' must be a finite number > 0 (or null); got 'fast'"),
    "val_fraction 1.5": Bad(conf={"val_fraction": 1.5}, needle="'val_fraction'"),
    "unknown key": Bad(conf={"epoch": 3}, needle="'epoch'"),
    "config not a mapping": Bad(conf=[1, 2], needle="mapping"),
    "device tpu": Bad(["--device", "tpu"], needle="'device'"),
    "device cuda": Bad(["--device", "cuda"], needle="'cuda'", needs_no_cuda=True),
    "epochs not a number": Bad(["--epochs", "many"], needle="--epochs"),
    "missing folder": Bad(images="missing", needle="{images}"),
    "folder without images": Bad(images="empty", needle="no images"),
    "out is a file": Bad(out="file", needle="{out}"),
}


class TestCli:
    @pytest.mark.parametrize("case", BAD.values(), ids=BAD.keys())
    def test_bad_input_is_one_error_line(self, case, images5, tmp_path, capsys):
        if case.needs_no_cuda and torch.cuda.is_available():
            pytest.skip("a CUDA GPU is available here")
        images = {"good": images5, "missing": tmp_path / "no_such_folder", "empty": tmp_path / "empty"}[case.images]
        if case.images == "empty":
            images.mkdir()
            (images / "notes.txt").write_text("no images here")
        out = tmp_path / "out"
        if case.out == "file":
            out.write_text("keep me")
        argv = ["train", "--images", str(images), "--out", str(out), "--device", "cpu", *case.args]
        if case.conf is not None:
            (tmp_path / "train.yaml").write_text(yaml.safe_dump(case.conf))
            argv += ["--config", str(tmp_path / "train.yaml")]
        code = cli_main(argv)
        captured = capsys.readouterr()
        lines = captured.err.splitlines()
        assert code == 2
        assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
        assert case.needle.format(images=images, out=out) in lines[0]
        assert "Traceback" not in captured.err + captured.out
        if case.out == "file":
            assert out.read_text() == "keep me"
        else:
            assert not out.exists()

    def test_trains_and_reports(self, images5, tmp_path, caplog):
        config = tmp_path / "train.yaml"
        config.write_text(yaml.safe_dump({**SMALL, "epochs": 5}))
        out = tmp_path / "out"
        with caplog.at_level(logging.INFO):
            code = cli_main(["train", "--images", str(images5), "--out", str(out), "--config", str(config),
                             "--epochs", "1"])
        assert code == 0 and (out / "best.pt").is_file()
        assert yaml.safe_load((out / "conf.yaml").read_text())["epochs"] == 1  # --epochs beats the file
        assert str(out / "best.pt") in caplog.text

    def test_defaults_come_from_the_api(self):
        from cae_lcd.cli.main import build_parser

        args = build_parser().parse_args(["train", "--images", "a", "b"])
        assert args.out == "runs/train" == str(training.main.__defaults__[0])
        assert args.images == ["a", "b"] and not args.restart and args.epochs is None

    def test_script_entry_point(self, tmp_path):
        """``python train.py`` is ``cae-lcd train``: a bad value is one line and exit code 2."""
        proc = subprocess.run([sys.executable, "train.py", "--images", str(tmp_path), "--out",
                               str(tmp_path / "out"), "--epochs", "0"], cwd=REPO, capture_output=True, text=True,
                              timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.splitlines() == ["error: 'epochs' must be an integer >= 1; got 0 (int)"]
        assert not (tmp_path / "out").exists()


class TestUnreadableImages:
    def test_skipped_by_name_and_counted(self, tmp_path, copy_sample_frames, caplog):
        folder = tmp_path / "images"
        copy_sample_frames([0, 40, 80], folder)
        (folder / "corrupt.jpg").write_bytes(b"\xff\xd8\xff\xe0 this is not a jpeg" * 8)
        assert cv2.imwrite(str(folder / "tiny.png"), np.full((4, 4), 128, np.uint8))
        (folder / "x.png").symlink_to(folder / "gone.png")
        (folder / "y.png").mkdir()
        bad = ["corrupt.jpg", "tiny.png", "x.png", "y.png"]
        with caplog.at_level(logging.WARNING, logger="cae.train"):
            s = main(folder, tmp_path / "run", {**SMALL, "epochs": 1})
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        for name in bad:
            assert any(str(folder / name) in w and w.startswith("skipping") for w in warnings), name
        assert s["images"] == 3 and s["unreadable"] == 4
        assert sorted(Path(p).name for p in s["skipped"]) == bad
        assert json.loads((tmp_path / "run" / "summary.json").read_text())["unreadable"] == 4
        split = json.loads((tmp_path / "run" / "split.json").read_text())
        assert len(split["train"]) + len(split["val"]) == 3

    def test_decompression_bomb_is_skipped(self, tmp_path, copy_sample_frames, caplog, capsys):
        folder = tmp_path / "images"
        copy_sample_frames([0, 40, 80], folder)
        bomb = write_bomb_png(folder / "bomb.png")
        assert bomb.stat().st_size < 1000
        with pytest.raises(ImageError, match="too large"):
            read_image(bomb)
        peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
        with caplog.at_level(logging.WARNING, logger="cae.train"):
            code = cli_main(["train", "--images", str(folder), "--out", str(tmp_path / "run"), "--device", "cpu",
                             "--epochs", "1"])
        assert code == 0
        assert "Traceback" not in capsys.readouterr().err
        assert any(str(bomb) in r.getMessage() and "too large" in r.getMessage() for r in caplog.records)
        assert json.loads((tmp_path / "run" / "summary.json").read_text())["skipped"] == [str(bomb)]
        assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before < 1 << 20  # < 1 GiB more


class TestListImages:
    def test_recursive_sorted(self, tmp_path, copy_sample_frames):
        copy_sample_frames([0, 1], tmp_path / "b")
        copy_sample_frames([2], tmp_path / "a" / "deeper")
        (tmp_path / "readme.txt").write_text("x")
        files = list_images(tmp_path)
        assert [f.relative_to(tmp_path).as_posix() for f in files] == \
            ["a/deeper/000000.jpg", "b/000000.jpg", "b/000001.jpg"]

    def test_lists_entries_that_only_look_like_images(self, tmp_path, copy_sample_frames):
        copy_sample_frames([0], tmp_path)
        (tmp_path / "x.png").symlink_to(tmp_path / "gone.png")
        (tmp_path / "y.png").mkdir()
        assert [f.name for f in list_images(tmp_path)] == ["000000.jpg", "x.png", "y.png"]

    def test_not_a_folder(self, tmp_path):
        with pytest.raises(ConfigError, match="not found"):
            list_images(tmp_path / "missing")
        (tmp_path / "file.jpg").write_bytes(b"x")
        with pytest.raises(ConfigError, match="not a folder"):
            list_images(tmp_path / "file.jpg")


class TestLoadImageFolder:
    def test_skips_unreadable(self, tmp_path, copy_sample_frames, caplog):
        files = copy_sample_frames([0, 1], tmp_path)
        bad = tmp_path / "bad.png"
        bad.write_bytes(b"garbage" * 20)
        data, used = load_image_folder([files[0], bad, files[1]])
        assert data.shape == (2, 256, 256, 3) and data.dtype == np.uint8
        assert used == [files[0], files[1]]
        assert f"skipping {bad}" in caplog.text
        with pytest.raises(ConfigError, match="none of the 1 images"):
            load_image_folder([bad])


class TestPlaceObjective:
    """Issue 28: the place term's conf keys are checked before anything is written; fine-tuning starts from the
    shipped weights and changes them."""

    @pytest.mark.parametrize("conf, key", [({"temperature": 0}, "temperature"), ({"contrastive": -1}, "contrastive"),
                                           ({"neighbours": -1}, "neighbours"), ({"recon_share": 0}, "recon_share"),
                                           ({"threads": 0}, "threads"), ({"init": 3}, "init"),
                                           ({"views": {"night": 1.5}}, "views.night"),
                                           ({"views": {"crop": -0.1}}, "views.crop"), ({"anchor": -1}, "anchor"),
                                           ({"views": {"grain": 0.5}}, "views.grain"), ({"blend": 0}, "blend"),
                                           ({"blend": 1.5}, "blend")])
    def test_bad_value_named_before_anything_is_written(self, images5, tmp_path, conf, key):
        out = tmp_path / "out"
        with pytest.raises(ConfigError, match=f"'{key}' must be"):
            main(images5, out, {**SMALL, **conf})
        assert not out.exists()

    @pytest.mark.parametrize("conf, match", [({"far": 1, "neighbours": 1}, "'far' .* must be larger"),
                                             ({"init": "missing.pt"}, "init: weights file not found")])
    def test_inconsistent_or_missing(self, images5, tmp_path, conf, match):
        out = tmp_path / "out"
        with pytest.raises(ConfigError, match=match):
            main(images5, out, {**SMALL, **conf})
        assert not out.exists()

    def test_a_fine_tune_is_blended_with_its_init_weights_once(self, images5, tmp_path):
        """``blend`` (0.5 by default where ``init`` is given): best.pt holds the midpoint of the fine-tuned weights
        (one epoch: last.pt's) and the init weights'; a finished run run again does not blend them a second time;
        ``blend: 1`` keeps the fine-tuned weights as trained."""
        conf = {**SMALL, "init": "shipped", "epochs": 1}
        main(images5, tmp_path / "half", conf)
        tuned = load_checkpoint(tmp_path / "half" / "last.pt")["state_dict"]
        shipped = load_checkpoint(cae.DEFAULT_WEIGHTS)["state_dict"]
        best = load_checkpoint(tmp_path / "half" / "best.pt")
        assert best["blend"] == 0.5 and not same_weights(tuned, shipped)
        for key, value in shipped.items():
            torch.testing.assert_close(best["state_dict"][key], 0.5 * tuned[key] + 0.5 * value)
        main(images5, tmp_path / "half", conf)  # finished: nothing trained, nothing blended again
        assert same_weights(tmp_path / "half" / "best.pt", best["state_dict"])
        main(images5, tmp_path / "whole", {**conf, "blend": 1.0})
        assert same_weights(tmp_path / "whole" / "best.pt", tmp_path / "whole" / "last.pt")
        assert "blend" not in load_checkpoint(tmp_path / "whole" / "best.pt")

    def test_fine_tune_from_shipped_loads_and_changes_the_weights(self, images12, tmp_path, monkeypatch):
        started_from = spy_first_epoch(monkeypatch)
        out = tmp_path / "tuned"
        assert cli_main(["train", "--images", str(images12), "--out", str(out), "--init", "shipped", "--epochs", "1",
                         "--device", "cpu"]) in (0, None)
        shipped = load_checkpoint(cae.DEFAULT_WEIGHTS)["state_dict"]
        assert same_weights(started_from[0], shipped)  # the first epoch trained from the shipped weights
        best = load_checkpoint(out / "best.pt")
        assert not same_weights(best["state_dict"], shipped)
        assert best["conf"]["init"] == "shipped" and "whitening" in best  # the whitening saved with the weights
        shipped_conf = load_checkpoint(cae.DEFAULT_WEIGHTS)["conf"]
        assert best["conf"]["still_cos"] == shipped_conf["still_cos"] < 0.999  # the init weights' own, carried
        assert best["conf"]["input_norm"] == shipped_conf["input_norm"] == "standardise"
        assert best["conf"]["lowpass"] == shipped_conf["lowpass"] > 0  # read alike: a fine-tune's codes comparable
        assert best["conf"]["lr"] == training.FINE_TUNE_LR < training.RANDOM_START_LR  # a fine-tune moves them less

    def test_small_images_are_read_through_the_low_pass_the_run_saves(self, sample_image, tmp_path):
        """``lowpass``: the training images as the detector will read them with the weights saved (a 64x32 frame
        blurred before it is brought up); None from a random start is 0."""
        folder = tmp_path / "small"
        folder.mkdir()
        for i in range(4):
            cv2.imwrite(str(folder / f"{i:06d}.png"), cv2.resize(sample_image(10 + i), (64, 32),
                                                                 interpolation=cv2.INTER_AREA))
        files = list_images(folder)
        blurred, _ = load_image_folder(files, 0.6)
        np.testing.assert_array_equal(blurred, np.stack([to_network_u8(read_image(f), 256, 0.6) for f in files]))
        assert not np.array_equal(blurred, load_image_folder(files)[0])
        main(folder, tmp_path / "lp", {**SMALL, "epochs": 1, "lowpass": 0.6})
        assert load_checkpoint(tmp_path / "lp" / "best.pt")["conf"]["lowpass"] == 0.6
        main(folder, tmp_path / "none", {**SMALL, "epochs": 1})
        assert load_checkpoint(tmp_path / "none" / "best.pt")["conf"]["lowpass"] == 0.0
        assert load_checkpoint(tmp_path / "none" / "best.pt")["conf"]["lr"] == training.RANDOM_START_LR  # lr: null


@pytest.mark.parametrize("chunk", [2, 64])
def test_the_place_step_in_cache_sized_chunks_is_the_whole_batch_gradient(sample_image, monkeypatch, chunk):
    """The place step on the CPU runs the network on ``CPU_BATCH`` images at a time (gradient caching: codes first,
    the place term's gradient with respect to them, then each chunk with its graph): the loss and every weight's
    gradient of the whole batch in one pass (the step written out here), up to float rounding; 8 real frames, a
    chunk of 2, and of 64 (one pass, as on a GPU)."""
    import torch.nn.functional as F

    from cae.contrastive import far_mask, info_nce, neighbour_partners, not_revisits, with_revisits
    from cae.encode import CPU_BATCH
    from cae.preprocess import to_network_u8

    assert CPU_BATCH < 8
    monkeypatch.setattr(training, "CPU_BATCH", chunk)
    frames = training._Frames(np.stack([to_network_u8(sample_image(i)) for i in range(0, 96, 8)]),
                              np.zeros(12, np.int64), np.arange(12))
    conf, picks, revisits, cpu = merge_conf(default_conf, {}), np.arange(0, 12, 3), np.zeros((0, 2), np.int64), \
        torch.device("cpu")
    picks = np.sort(np.r_[picks, picks + 1])
    model = ConvAutoencoder()
    got = training._place_step(model, frames, picks, np.random.default_rng(0), conf, cpu, revisits)
    chunked = {k: p.grad.clone() for k, p in model.named_parameters()}
    model.zero_grad(set_to_none=True)
    rng = np.random.default_rng(0)  # the whole batch at once, the draws in the same order
    partners = with_revisits(neighbour_partners(frames.folder, frames.position, picks, conf["neighbours"], rng),
                             picks, revisits, conf["revisit_share"], rng)
    target, view_a = training._view(training._to_batch(frames.images[picks], cpu), rng, conf)
    _, view_b = training._view(training._to_batch(frames.images[partners], cpu), rng, conf)
    code_a, code_b = model.encoder.forward_map(view_a), model.encoder.forward_map(view_b).flatten(1)
    n_rec = max(1, int(round(conf["recon_share"] * len(picks))))
    neg = torch.as_tensor(far_mask(frames.folder[picks], frames.position[picks], conf["far"])
                          & not_revisits(picks, revisits))
    loss = F.binary_cross_entropy_with_logits(model.decoder(code_a[:n_rec]), target[:n_rec]) + \
        conf["contrastive"] * info_nce(code_a.flatten(1), code_b, neg, conf["temperature"])
    loss.backward()
    assert got == pytest.approx(loss.item(), rel=1e-5)
    for name, p in model.named_parameters():
        torch.testing.assert_close(chunked[name], p.grad, rtol=1e-3, atol=1e-6, msg=name)
