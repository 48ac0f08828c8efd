"""A hostile user's corpus against ``cae-lcd detect`` and ``cae-lcd evaluate``, table-driven.

What every case must show: the exit code; exactly one ``error:`` line naming the key or file (or, for a bad frame,
one warning line naming the file, the frame counted); never a traceback; never a wrong result with exit 0; nothing
already written lost; the results of the good frames unchanged.

The sequence is 16 real frames of the bundled sample (8 of the first pass, 8 revisiting them) with
``search.exclude_recent: 8``, so a run takes about a second.
"""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch

from cae_lcd.cli.main import main
from cae_lcd.core.errors import printable
from cae_lcd.core.images import read_image
from retrieval.run_folder import RunFolder

REPO = Path(__file__).parents[2]
FRAMES = [*range(0, 8), *range(50, 58)]  # sample frames: 8 first-pass, 8 revisiting them (loops 8.. -> 0..)
CONF = "search: {exclude_recent: 8}\ncalibration: {enabled: false}  # 16 frames are too few to calibrate on\n"


def run_cli(args, capsys):
    """``cae-lcd ARGS`` in-process; returns (exit code, stderr)."""
    capsys.readouterr()
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def one_error_line(code, err, *fragments, exit_code=2):
    assert code == exit_code, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


def make_sequence(dst: Path, indices=FRAMES, calib: bool = True) -> Path:
    """A KITTI-layout copy of sample frames ``indices`` renumbered from 0, with calib.txt."""
    (dst / "image_0").mkdir(parents=True)
    for n, i in enumerate(indices):
        shutil.copyfile(REPO / "retrieval" / "sample" / "image_0" / f"{i:06d}.jpg", dst / "image_0" / f"{n:06d}.jpg")
    if calib:
        shutil.copyfile(REPO / "retrieval" / "sample" / "calib.txt", dst / "calib.txt")
    return dst


@pytest.fixture(scope="module")
def conf_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("conf") / "small.yaml"
    path.write_text(CONF)
    return path


@pytest.fixture(scope="module")
def baseline(tmp_path_factory, conf_file):
    """A clean run over the 16 frames: ``(sequence, run folder, loops.csv bytes)``."""
    root = tmp_path_factory.mktemp("baseline")
    seq = make_sequence(root / "seq")
    assert main(["detect", str(seq), "--out", str(root / "run"), "--config", str(conf_file), "--no-progress"]) == 0
    loops = (root / "run" / "loops.csv").read_bytes()
    assert loops.count(b"\n") > 4, "the small sequence must have loops for these tests to mean something"
    return seq, root / "run", loops


def loops_rows(run: Path) -> list[tuple[int, int]]:
    return [tuple(map(int, r[:2])) for r in RunFolder(run).read_loops()]


# ------------------------------------------------------------------------------------------------ bad frames
def _bomb_png(path: Path) -> None:
    """A valid tiny PNG whose header claims 40000 x 40000 pixels (a decompression bomb)."""
    data = bytearray(cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
    ihdr = data[12:29]  # b"IHDR" + 13 bytes
    ihdr[4:12] = struct.pack(">II", 40000, 40000)
    data[12:29] = ihdr
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(ihdr)))
    path.write_bytes(bytes(data))


def _signed(dtype):
    def write(path: Path) -> None:
        img = read_image(REPO / "retrieval" / "sample" / "image_0" / "000003.jpg").astype(np.float64)
        assert cv2.imwrite(str(path), (img * 100 - 12000).astype(dtype))
    return write


BAD_FRAMES = [  # (name, writer, readable): appended after the good frames, so their ids do not move
    ("000016.png", lambda p: cv2.imwrite(str(p), np.full((4, 4), 128, np.uint8)), False),  # under 8x8
    ("000017.png", lambda p: cv2.imwrite(str(p), np.full((1, 2000), 128, np.uint8)), False),  # a 1x2000 strip
    ("000018.tif", _signed(np.int16), True),  # signed 16-bit with negative values
    ("000019.tif", _signed(np.int32), True),  # signed 32-bit
    ("000020.png", _bomb_png, False),  # header says 40000x40000
    ("000021.png", lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50), False),  # corrupt
    (os.fsdecode(b"000022\xff.png"), lambda p: shutil.copyfile(REPO / "retrieval" / "sample" / "image_0" /
                                                               "000060.jpg", p), True),  # name not UTF-8
    ("000023.png", lambda p: p.symlink_to(p.parent / "does-not-exist.png"), False),  # broken link
    ("000024.png", lambda p: os.mkfifo(p), False),  # a FIFO: must not block
    ("000025.png", lambda p: p.mkdir(), False),  # a folder named like an image
    (os.fsdecode(b"000026\xfe.png"), lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"x" * 40),
     False),  # unreadable, and its name not UTF-8
]


class TestBadFrames:
    def test_bad_frames_skipped_named_counted(self, tmp_path, capsys, caplog, baseline, conf_file):
        seq = make_sequence(tmp_path / "seq")
        for name, write, _ in BAD_FRAMES:
            write(seq / "image_0" / name)
        code, err = run_cli(["detect", seq, "--out", tmp_path / "run", "--config", conf_file, "--no-progress"],
                            capsys)
        assert code == 0, err
        assert "Traceback" not in err
        summary = RunFolder(tmp_path / "run").read_summary()
        unreadable = [n for n, _, ok in BAD_FRAMES if not ok]
        assert summary["frames"] == 16 + len(BAD_FRAMES)
        assert sorted(summary["unreadable_files"]) == sorted(unreadable)
        assert summary["keyframes"] + summary["gated_out"] == 16 + len(BAD_FRAMES) - len(unreadable)
        warnings = [r.getMessage() for r in caplog.records if "skipping frame" in r.getMessage()]
        assert all("\n" not in w and w.encode("utf-8") for w in warnings)  # a name not UTF-8 written with escapes
        assert len(warnings) == len(unreadable)
        for name in unreadable:
            assert sum(printable(name) in line for line in warnings) == 1, (name, warnings)
        # the good frames' results are those of a clean run
        good = [(q, m) for q, m in loops_rows(tmp_path / "run") if q < 16]
        assert good == loops_rows(baseline[1])

    def test_rerun_resumes_past_bad_frames(self, tmp_path, capsys, caplog, conf_file):
        seq = make_sequence(tmp_path / "seq", FRAMES[:10])
        _bomb_png(seq / "image_0" / "000010.png")
        args = ["detect", seq, "--out", tmp_path / "run", "--config", conf_file, "--no-progress"]
        assert run_cli(args, capsys)[0] == 0
        code, err = run_cli(args, capsys)
        assert code == 0, err
        summary = RunFolder(tmp_path / "run").read_summary()
        assert summary["unreadable"] == 1 and summary["resumed_at"] == 11 and summary["processed_this_run"] == 0


# ------------------------------------------------------------------------------------- resuming other data
class TestResumeIntoOtherData:
    @pytest.mark.parametrize("change, fragment", [
        ("other_sequence", "has changed since it was processed"),
        ("file_removed", "was 000005.jpg, now it is 000006.jpg"),
        ("fewer_files", "folder has only"),
    ])
    def test_refused_and_tables_kept(self, tmp_path, capsys, conf_file, change, fragment):
        seq = make_sequence(tmp_path / "seq")
        out = tmp_path / "run"
        assert run_cli(["detect", seq, "--out", out, "--config", conf_file, "--no-progress"], capsys)[0] == 0
        before = {p.name: p.read_bytes() for p in out.iterdir() if p.suffix in (".csv", ".json", ".yaml")}
        if change == "other_sequence":  # same names, other images (like sequence 00 then 90)
            shutil.rmtree(seq)
            make_sequence(seq, [*range(10, 18), *range(60, 68)])
        elif change == "file_removed":
            (seq / "image_0" / "000005.jpg").unlink()
        else:
            for n in range(10, 16):
                (seq / "image_0" / f"{n:06d}.jpg").unlink()
        code, err = run_cli(["detect", seq, "--out", out, "--config", conf_file, "--no-progress"], capsys)
        one_error_line(code, err, "built from other images", fragment)
        assert {p.name: p.read_bytes() for p in out.iterdir() if p.name in before} == before

    def test_file_added_at_the_end_resumes(self, tmp_path, capsys, conf_file):
        seq = make_sequence(tmp_path / "seq")
        out = tmp_path / "run"
        assert run_cli(["detect", seq, "--out", out, "--config", conf_file, "--no-progress"], capsys)[0] == 0
        shutil.copyfile(REPO / "retrieval" / "sample" / "image_0" / "000058.jpg", seq / "image_0" / "000016.jpg")
        code, err = run_cli(["detect", seq, "--out", out, "--config", conf_file, "--no-progress"], capsys)
        assert code == 0, err
        summary = RunFolder(out).read_summary()
        assert summary["resumed_at"] == 16 and summary["frames"] == 17 and summary["processed_this_run"] == 1


# ----------------------------------------------------------------------------------------- damaged database
def _flip_code_bytes(db_path: Path, frame_id: int) -> None:
    with h5py.File(db_path, "r") as f:  # the keyframe's row of the code matrix, in its (uncompressed) chunk
        n = int(f.attrs["committed"])
        row = int(np.flatnonzero(f["frames/frame_id"][:n][f["frames/kind"][:n] == 0] == frame_id)[0])
        codes = f["codes"]
        per_chunk = codes.chunks[0]
        chunk = codes.id.get_chunk_info_by_coord((row // per_chunk * per_chunk, 0))
        offset = chunk.byte_offset + (row % per_chunk) * codes.shape[1] * codes.dtype.itemsize - 100 + 2
    with open(db_path, "r+b") as fh:
        fh.seek(offset + 100)
        byte = fh.read(1)
        fh.seek(offset + 100)
        fh.write(bytes([byte[0] ^ 0x5A]))


class TestDamagedDatabase:
    def test_bit_flip_reported_tables_kept(self, tmp_path, capsys, baseline, conf_file):
        seq, clean, _ = baseline
        out = tmp_path / "run"
        shutil.copytree(clean, out)
        before = (out / "loops.csv").read_bytes()
        _flip_code_bytes(out / "keyframes.h5", 3)
        code, err = run_cli(["detect", seq, "--out", out, "--config", conf_file, "--no-progress"], capsys)
        one_error_line(code, err, "keyframes.h5 is damaged", "fail their checksum")  # the block holding frame 3
        assert (out / "loops.csv").read_bytes() == before
        code, err = run_cli(["evaluate", out, "--gt", REPO / "retrieval" / "sample" / "loops.txt", "--out",
                             tmp_path / "ev"], capsys)
        one_error_line(code, err, "damaged")
        assert not (tmp_path / "ev" / "evaluation.json").exists()

    def test_truncated_database(self, tmp_path, capsys, baseline, conf_file):
        seq, clean, _ = baseline
        out = tmp_path / "run"
        shutil.copytree(clean, out)
        data = (out / "keyframes.h5").read_bytes()
        (out / "keyframes.h5").write_bytes(data[: len(data) // 3])
        code, err = run_cli(["detect", seq, "--out", out, "--config", conf_file, "--no-progress"], capsys)
        one_error_line(code, err, "damaged")
        assert (out / "keyframes.h5").stat().st_size == len(data) // 3  # left as it was

    def test_locked_by_another_process(self, tmp_path, capsys, baseline, conf_file):
        seq, clean, _ = baseline
        out = tmp_path / "run"
        shutil.copytree(clean, out)
        holder = subprocess.Popen([sys.executable, "-c", textwrap.dedent(f"""
            import h5py, sys, time
            f = h5py.File({str(out / 'keyframes.h5')!r}, "a")
            print("ready", flush=True)
            sys.stdin.read()
            """)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        try:
            assert holder.stdout.readline().strip() == "ready"
            code, err = run_cli(["detect", seq, "--out", out, "--config", conf_file, "--no-progress"], capsys)
            one_error_line(code, err, "in use by another process")
        finally:
            holder.communicate("", timeout=30)


# ----------------------------------------------------------------------------------- values that make no sense
BAD_CONFS = [
    ("search: {k: 0}", "'search.k' must be an integer >= 1"),
    ("search: {k: -1}", "'search.k'"),
    ("search: {k: ten}", "'search.k'"),
    ("search: {k: 2.5}", "'search.k'"),
    ("search: {exclude_recent: -10}", "'search.exclude_recent' must be an integer >= 0"),
    ("search: {min_score: high}", "'search.min_score'"),
    ("geometry: {threshold: .nan}", "'geometry.threshold' must be a finite number"),
    ("geometry: {confidence: 2.0}", "'geometry.confidence'"),
    ("matcher: {ratio: -1}", "'matcher.ratio'"),
    ("matcher: {ratio: 2.0}", "'matcher.ratio'"),
    ("policy: {min_inliers: -5}", "'policy.min_inliers'"),
    ("features: {max_features: -1}", "'features.max_features'"),
    ("features: {max_features: 1000000000000}", "'features.max_features'"),  # beyond OpenCV's C int
    ("search: {k: 3}\nsearch: {k: 4}", "key 'search' given twice"),
    ("a: " + "[" * 5000 + "]" * 5000, "nested more than 32 levels deep"),
    ("gate: {image_size: 0}", "'gate.image_size'"),
    ("runtime: {threads: -2}", "'runtime.threads'"),
    ("descriptor: {device: tpu}", "'descriptor.device'"),
    ("descriptor: {name: nope}", "unknown global descriptor 'nope'"),
    ("search: {kk: 3}", "unknown config key 'search.kk'"),
    ("search: 5", "'search' must be a mapping"),
    ("search: [1, 2", "cannot parse config file"),
    ("policy: {check_all: 1}", "'policy.check_all' must be true or false"),
]


class TestBadConfig:
    @pytest.mark.parametrize("text, fragment", BAD_CONFS, ids=[c[0][:40] for c in BAD_CONFS])
    def test_refused_before_anything_is_written(self, tmp_path, capsys, baseline, text, fragment):
        bad = tmp_path / "bad.yaml"
        bad.write_text(text + "\n")
        code, err = run_cli(["detect", baseline[0], "--out", tmp_path / "run", "--config", bad, "--no-progress"],
                            capsys)
        one_error_line(code, err, fragment)
        assert not (tmp_path / "run").exists()

    def test_existing_run_untouched_and_corrected_run_works(self, tmp_path, capsys, baseline, conf_file):
        seq, clean, loops = baseline
        out = tmp_path / "run"
        shutil.copytree(clean, out)
        files = {p.name: p.read_bytes() for p in out.iterdir()}
        bad = tmp_path / "bad.yaml"
        bad.write_text(CONF + "policy: {min_inliers: -1}\n")
        one_error_line(*run_cli(["detect", seq, "--out", out, "--config", bad, "--no-progress"], capsys),
                       "'policy.min_inliers'")
        assert {p.name: p.read_bytes() for p in out.iterdir()} == files
        code, err = run_cli(["detect", seq, "--out", tmp_path / "fresh", "--config", conf_file, "--no-progress"],
                            capsys)
        assert code == 0 and (tmp_path / "fresh" / "loops.csv").read_bytes() == loops

    def test_binary_config_file(self, tmp_path, capsys, baseline):
        bad = tmp_path / "bad.yaml"
        bad.write_bytes(bytes(range(256)) * 4)
        code, err = run_cli(["detect", baseline[0], "--out", tmp_path / "run", "--config", bad], capsys)
        one_error_line(code, err, "cannot parse config file")

    def test_nan_weights(self, tmp_path, capsys, baseline):
        import cae
        from cae.weights import save_checkpoint

        enc = cae.load_encoder(device="cpu")
        with torch.no_grad():
            next(enc.parameters()).fill_(float("nan"))
        save_checkpoint(tmp_path / "nan.pt", enc, {})
        code, err = run_cli(["detect", baseline[0], "--out", tmp_path / "run", "--weights", tmp_path / "nan.pt"],
                            capsys)
        one_error_line(code, err, "NaN or infinite")
        assert not (tmp_path / "run").exists()

    def test_unknown_option(self, capsys):
        one_error_line(*run_cli(["detect", "--bogus"], capsys), "unrecognized arguments: --bogus")


# ------------------------------------------------------------------------------------------------- --out
OUTS = [
    ("a_file", "exists and is not a folder"),
    ("under_a_file", "a parent of it is a file"),
    ("/dev/null", "exists and is not a folder"),
    ("/sys/cae_lcd_test_out", "cannot be created"),
]


class TestBadOut:
    @pytest.mark.parametrize("where, fragment", OUTS)
    def test_refused(self, tmp_path, capsys, baseline, where, fragment):
        if where == "a_file":
            out = tmp_path / "f"
            out.write_text("keep me")
        elif where == "under_a_file":
            (tmp_path / "f").write_text("keep me")
            out = tmp_path / "f" / "run"
        else:
            out = Path(where)
            if where.startswith("/sys") and not Path("/sys").is_dir():
                pytest.skip("no /sys here")
        code, err = run_cli(["detect", baseline[0], "--out", out, "--no-progress"], capsys)
        one_error_line(code, err, fragment)
        if (tmp_path / "f").exists():
            assert (tmp_path / "f").read_text() == "keep me"


    @pytest.mark.parametrize("found", ["loops.csv", "summary.json"])
    def test_results_without_a_database_are_kept(self, tmp_path, capsys, baseline, conf_file, found):
        """An --out holding someone's ``loops.csv`` (or a run whose keyframes.h5 was removed): was overwritten."""
        out = tmp_path / "run"
        out.mkdir()
        (out / found).write_text("keep me")
        code, err = run_cli(["detect", baseline[0], "--out", out, "--config", conf_file, "--no-progress"], capsys)
        one_error_line(code, err, f"holds {found} but no keyframes.h5")
        assert [p.name for p in out.iterdir()] == [found] and (out / found).read_text() == "keep me"

    def test_other_files_are_left_alone(self, tmp_path, capsys, baseline, conf_file):
        out = tmp_path / "run"
        out.mkdir()
        (out / "notes.txt").write_text("mine")
        code, err = run_cli(["detect", baseline[0], "--out", out, "--config", conf_file, "--no-progress"], capsys)
        assert code == 0, err
        assert (out / "notes.txt").read_text() == "mine" and (out / "loops.csv").read_bytes() == baseline[2]


# ----------------------------------------------------------------------------------------------- disk full
class TestDiskFull:
    def test_clean_error_then_resume_to_the_same_result(self, tmp_path, baseline, conf_file):
        """A file-size limit (RLIMIT_FSIZE, no root needed) stands in for a full disk. Frames go into the store's
        columns two at a time (``runtime.flush_every``), so the store grows during the run (the default moves them
        256 at a time: these 16 frames would be written once, at the end)."""
        seq, _, loops = baseline
        out = tmp_path / "run"
        conf_file = tmp_path / "blocks.yaml"
        conf_file.write_text(CONF + "runtime: {flush_every: 2}\n")
        script = textwrap.dedent("""
            import resource, signal, sys
            signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
            import retrieval.database as database
            database.MIN_FREE_BYTES = 1 << 20
            limit = (1 << 20) + 300_000
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
            from cae_lcd.cli.main import main
            sys.exit(main(sys.argv[1:]))
            """)
        args = ["detect", str(seq), "--out", str(out), "--config", str(conf_file), "--no-progress"]
        proc = subprocess.run([sys.executable, "-c", script, *args], capture_output=True, text=True, cwd=REPO,
                              timeout=300)
        assert proc.returncode == 2, proc.stderr[-2000:]
        one_error_line(proc.returncode, proc.stderr, "not enough space", "run again to resume")
        proc = subprocess.run([sys.executable, "-m", "cae_lcd.cli.main", *args], capture_output=True, text=True, cwd=REPO,
                              timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert "resuming at frame" in proc.stderr
        assert (out / "loops.csv").read_bytes() == loops


# --------------------------------------------------------------------------------------------- bad metadata
BAD_METADATA = [
    ("calib.txt", "P0: a b c d e f g h i j k l\n", "calib.txt, line 1"),
    ("times.txt", "0.0\nabc\n", "times.txt, line 2"),
    ("poses.txt", "1 0 0 0 0 1 0 0 0 0 1\n", "poses.txt, line 1: expected 12 numbers"),
    ("poses.txt", "1 0 0 nan 0 1 0 0 0 0 1 0\n", "poses.txt, line 1: NaN"),
    ("loops.txt", "x y\n", "loops.txt: not a ground-truth file"),
]


class TestBadMetadata:
    @pytest.mark.parametrize("name, text, fragment", BAD_METADATA, ids=[f"{m[0]}:{m[1][:8]}" for m in BAD_METADATA])
    def test_refused_with_file_and_line(self, tmp_path, capsys, conf_file, name, text, fragment):
        seq = make_sequence(tmp_path / "seq", FRAMES[:10])
        (seq / name).write_text(text)
        code, err = run_cli(["detect", seq, "--out", tmp_path / "run", "--config", conf_file, "--no-progress"],
                            capsys)
        one_error_line(code, err, fragment)


# --------------------------------------------------------------------------------------------------- evaluate
def _bad_eval(case: str, run: Path, tmp: Path) -> tuple[list, str | None]:
    """Sets up one hostile ``evaluate`` input; returns (args, expected error fragment or None for a warning)."""
    gt = REPO / "retrieval" / "sample" / "loops.txt"
    if case == "huge_index":
        (run / "loops.csv").write_text("query,match,score,matches,inliers\n1000000000000,0,0.9,10,60\n")
        return [run, "--gt", gt], "frame ids must be integers"
    if case == "binary_loops":
        (run / "loops.csv").write_bytes(bytes(range(256)) * 8)
        return [run, "--gt", gt], "loops.csv"
    if case == "nan_query":
        (run / "loops.csv").write_text("query,match,score,matches,inliers\nnan,0,0.9,10,60\n")
        return [run, "--gt", gt], "frame ids must be integers"
    if case == "nan_poses":
        poses = tmp / "poses.txt"
        poses.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 5 + "1 0 0 inf 0 1 0 0 0 0 1 0\n")
        return [run, "--gt", poses], "poses.txt, line 6"
    if case == "out_is_a_file":
        (tmp / "f").write_text("x")
        return [run, "--gt", gt, "--out", tmp / "f"], "exists and is not a folder"
    if case == "bad_summary_and_conf":
        (run / "summary.json").write_text("{not json")
        (run / "conf.yaml").write_text("policy: [1, 2\n")
        return [run, "--gt", gt, "--out", tmp / "ev"], None
    if case == "summary_wrong_types":
        (run / "summary.json").write_text('{"frames": "many", "sequence": 5}')
        (run / "conf.yaml").write_text("policy: high\nsearch: {k: ten}\n")
        return [run, "--gt", gt, "--out", tmp / "ev"], None
    raise AssertionError(case)


EVAL_CASES = ["huge_index", "binary_loops", "nan_query", "nan_poses", "out_is_a_file", "bad_summary_and_conf",
              "summary_wrong_types"]


class TestEvaluateHostile:
    @pytest.mark.parametrize("case", EVAL_CASES)
    def test_case(self, tmp_path, capsys, caplog, baseline, case):
        run = tmp_path / "run"
        shutil.copytree(baseline[1], run)
        args, fragment = _bad_eval(case, run, tmp_path)
        code, err = run_cli(["evaluate", *args], capsys)
        assert "Traceback" not in err
        if fragment is not None:
            one_error_line(code, err, fragment)
        else:
            assert code == 0, err
            assert any(r.levelname == "WARNING" for r in caplog.records)

    def test_empty_ground_truth_warns(self, tmp_path, capsys, caplog, baseline):
        (tmp_path / "gt.txt").write_text("# no loops here\n")
        code, err = run_cli(["evaluate", baseline[1], "--gt", tmp_path / "gt.txt", "--out", tmp_path / "ev"], capsys)
        assert code == 0 and "Traceback" not in err
        assert any("holds no loop pair" in r.getMessage() for r in caplog.records if r.levelname == "WARNING")


# ------------------------------------------------------------------------------------------------ odd folders
class TestOddFolders:
    def test_a_camera_standing_still_reports_no_loop(self, tmp_path, capsys):
        """60 copies of one frame, the default conf: the calibration cannot be made (no far-side pair), and the
        fixed policy it falls back to counts the stop as one frame (was: a loop for each frame past the 50th)."""
        (tmp_path / "seq").mkdir()
        for n in range(60):
            shutil.copyfile(REPO / "retrieval" / "sample" / "image_0" / "000010.jpg", tmp_path / "seq" / f"{n:06d}.jpg")
        code, err = run_cli(["detect", tmp_path / "seq", "--out", tmp_path / "run", "--no-progress"], capsys)
        assert code == 0 and "Traceback" not in err, err
        assert loops_rows(tmp_path / "run") == []

    def test_unpadded_names_run_in_number_order(self, tmp_path, capsys, baseline, conf_file):
        """``0.jpg ... 15.jpg``: the same loops as ``000000.jpg ...`` (text order put 10..15 before 2)."""
        seq = make_sequence(tmp_path / "seq")
        for p in (seq / "image_0").iterdir():
            p.rename(p.with_name(f"{int(p.stem)}{p.suffix}"))
        code, err = run_cli(["detect", seq, "--out", tmp_path / "run", "--config", conf_file, "--no-progress"], capsys)
        assert code == 0, err
        assert loops_rows(tmp_path / "run") == loops_rows(baseline[1])
