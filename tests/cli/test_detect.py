"""``cae-lcd detect`` end to end: in-process through ``cae_lcd.cli.main.main``, plus one real subprocess."""

import csv
import json
import logging
import shutil
import subprocess
import sys

import cv2
import h5py
import numpy as np
import pytest
import yaml

from cae_lcd.core.images import read_image
from cae_lcd.cli.main import main
from retrieval.database import KeyframeDatabase, KeyframeRecord
from retrieval.detect import SAMPLE_DIR
from retrieval.detector import resolve_conf


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.reader(f))


def run_detect(args, capsys):
    """Runs ``cae-lcd detect ARGS --no-progress`` in-process; returns (exit code, stderr)."""
    capsys.readouterr()
    code = main(["detect", *map(str, args), "--no-progress"])
    return code, capsys.readouterr().err


def assert_one_line_error(code, err, *fragments):
    assert code == 2
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1, err
    for fragment in fragments:
        assert fragment in lines[0]
    return lines[0]


class TestDetectSample:
    def test_tables_and_summary(self, cli_sample_run):
        code, out = cli_sample_run
        assert code == 0
        loops = read_csv(out / "loops.csv")
        assert loops[0] == ["query", "match", "score", "matches", "inliers", "seq_score", "confidence",
                            "query_time", "match_time", "query_source", "match_source"]
        cands = read_csv(out / "candidates.csv")
        assert cands[0] == ["query", "candidate", "score", "matches", "inliers", "seq_score", "confidence", "accepted",
                            "query_time", "candidate_time", "query_source", "candidate_source"]
        # each frame's stamp (the sample's times.txt) and file, to join with the user's own trajectory
        times = np.loadtxt(SAMPLE_DIR / "times.txt")
        for row in loops[1:] + cands[1:]:
            q, m = int(row[0]), int(row[1])
            assert float(row[-4]) == pytest.approx(times[q], abs=1e-9) and float(row[-3]) == pytest.approx(times[m])
            assert row[-2:] == [f"image_0/{q:06d}.jpg", f"image_0/{m:06d}.jpg"]
        tum = np.loadtxt(out / "loops_tum.txt")
        assert np.allclose(tum, [[times[int(r[0])], times[int(r[1])]] for r in loops[1:]])
        summary = json.loads((out / "summary.json").read_text())
        gt = summary["ground_truth"]
        assert gt["precision"] == 1.0
        assert gt["recall"] >= 0.9
        assert summary["frames"] == 100 and summary["keyframes"] == 100 and summary["resumed_at"] == 0
        assert summary["unreadable"] == 0 and summary["gated_out"] == 0
        assert summary["loops"] == len(loops) - 1 == gt["detections"]
        assert set(summary["ms_per_frame"]) >= {"encode", "features", "verify", "total"}

    def test_loops_consistent_with_candidates(self, cli_sample_run):
        _, out = cli_sample_run
        summary = json.loads((out / "summary.json").read_text())
        accept_at = summary["calibration"]["accept_at_confidence"]
        loops = [tuple(r[:7]) for r in read_csv(out / "loops.csv")[1:]]
        accepted = [tuple(r[:7]) for r in read_csv(out / "candidates.csv")[1:] if r[7] == "1"]
        assert sorted(loops) == sorted(accepted)
        for q, m, score, matches, inliers, seq_score, confidence in loops:
            assert int(q) - int(m) >= 50
            assert float(confidence) >= accept_at  # the calibrated rule: expected false loops <= 0.05 per path
            assert -1 <= float(score) <= 1
        queries = [q for q, *_ in loops]
        assert len(queries) == len(set(queries))  # at most one loop per query

    def test_resolved_conf_and_database(self, cli_sample_run, detect_conf):
        _, out = cli_sample_run
        saved = yaml.safe_load((out / "conf.yaml").read_text())
        assert saved == resolve_conf(detect_conf)
        with KeyframeDatabase(out / "keyframes.h5", mode="r") as db:
            assert len(db) == 100 and db.last_frame_id() == 99
            assert db.conf == {k: v for k, v in saved.items() if k != "runtime"}

    def test_resume_after_interruption(self, cli_sample_run, detect_conf, detect_config_args, tmp_path, capsys):
        """Simulates a run killed after frame 89 (its last block of frames written, never committed, and its
        write-ahead log lost), then runs again."""
        _, out = cli_sample_run
        run = tmp_path / "run"
        blocks = {**detect_conf, "runtime": {**detect_conf.get("runtime", {}), "flush_every": 30}}
        (tmp_path / "blocks.yaml").write_text(yaml.safe_dump(blocks))
        code, err = run_detect(["--out", run, "--config", tmp_path / "blocks.yaml"], capsys)  # blocks of 30 frames
        assert code == 0, err
        with h5py.File(run / "keyframes.h5", "a") as f:  # frames 90-99 written, never committed (a kill -9)
            assert f["blocks/end"][:4].tolist() == [30, 60, 90, 100] and f["frames/frame_id"][90] == 90
            f.attrs["committed"] = 90
        assert not (run / "keyframes.h5.log").exists()  # emptied and removed when the run closed
        code, err = run_detect(["--out", run, *detect_config_args], capsys)
        assert code == 0, err
        summary = json.loads((run / "summary.json").read_text())
        assert summary["resumed_at"] == 90
        assert summary["processed_this_run"] == 10
        assert summary["keyframes"] == 100
        assert read_csv(run / "loops.csv") == read_csv(out / "loops.csv")
        assert summary["ground_truth"] == json.loads((out / "summary.json").read_text())["ground_truth"]


@pytest.fixture(scope="module")
def short_conf_file(tmp_path_factory):
    """Short exclusion window, so that a few frames already produce loops."""
    path = tmp_path_factory.mktemp("short_conf") / "short.yaml"
    path.write_text(yaml.safe_dump({"search": {"exclude_recent": 3}, "calibration": {"enabled": False}}))
    return path


# sample frames 0, 1, 2 and their revisits 50, 51, 52: renumbered 0..5, so 3->0, 4->1, 5->2 are true loops
FOLDER_FRAMES = [0, 1, 2, 50, 51, 52]


@pytest.fixture(scope="module")
def folder_runs(tmp_path_factory, copy_sample_frames, short_conf_file):
    """The same six frames as grey JPEG, colour (BGR) PNG and 16-bit PNG folders, each run through detect."""
    root = tmp_path_factory.mktemp("formats")
    variants = {
        "grey": dict(transform=None, ext=".jpg"),
        "colour": dict(transform=lambda g: cv2.cvtColor(g, cv2.COLOR_GRAY2BGR), ext=".png"),
        "16bit": dict(transform=lambda g: g.astype(np.uint16) * 257, ext=".png"),
    }
    runs = {}
    for name, kw in variants.items():
        copy_sample_frames(FOLDER_FRAMES, root / name, **kw)
        out = root / f"{name}_out"
        code = main(["detect", str(root / name), "--out", str(out), "--config", str(short_conf_file),
                     "--no-progress"])
        runs[name] = (code, root / name, out)
    return runs


class TestDetectFolders:
    def test_inputs_are_what_they_claim(self, folder_runs):
        assert read_image(folder_runs["colour"][1] / "000000.png").shape == (188, 620, 3)
        img16 = read_image(folder_runs["16bit"][1] / "000000.png")
        assert img16.dtype == np.uint16 and img16.max() > 255

    @pytest.mark.parametrize("name", ["grey", "colour", "16bit"])
    def test_format_runs(self, folder_runs, name):
        code, _, out = folder_runs[name]
        assert code == 0
        summary = json.loads((out / "summary.json").read_text())
        assert summary["frames"] == 6 and summary["keyframes"] == 6
        assert summary["unreadable"] == 0 and summary["gated_out"] == 0
        assert "ground_truth" not in summary  # a plain folder has none
        loops = {(int(r[0]), int(r[1])) for r in read_csv(out / "loops.csv")[1:]}
        assert loops == {(3, 0), (4, 1), (5, 2)}

    def test_formats_give_same_codes(self, folder_runs):
        codes = {}
        for name, (_, _, out) in folder_runs.items():
            with KeyframeDatabase(out / "keyframes.h5", mode="r") as db:
                codes[name] = db.codes()[0]
        np.testing.assert_allclose(codes["colour"], codes["grey"], atol=1e-6)
        np.testing.assert_allclose(codes["16bit"], codes["grey"], atol=1e-6)

    def test_corrupt_image_skipped(self, tmp_path, copy_sample_frames, capsys, caplog):
        copy_sample_frames(range(12), tmp_path / "imgs")
        (tmp_path / "imgs" / "000005b.jpg").write_bytes(b"\xff\xd8\xff garbage, not a JPEG" * 20)
        code, err = run_detect([tmp_path / "imgs", "--out", tmp_path / "out"], capsys)
        assert code == 0, err
        summary = json.loads((tmp_path / "out" / "summary.json").read_text())
        assert summary["frames"] == 13
        assert summary["unreadable"] == 1 and summary["unreadable_files"] == ["000005b.jpg"]
        assert summary["keyframes"] == 12
        assert "000005b.jpg" in caplog.text and "skipping frame 6" in caplog.text
        with KeyframeDatabase(tmp_path / "out" / "keyframes.h5", mode="r") as db:
            assert [r.frame_id for r in db] == [0, 1, 2, 3, 4, 5, 7, 8, 9, 10, 11, 12]


class TestDetectErrors:
    def test_missing_folder(self, tmp_path, capsys):
        code, err = run_detect([tmp_path / "missing", "--out", tmp_path / "out"], capsys)
        assert_one_line_error(code, err, "not found", "missing")

    def test_empty_folder(self, tmp_path, capsys):
        (tmp_path / "empty").mkdir()
        code, err = run_detect([tmp_path / "empty", "--out", tmp_path / "out"], capsys)
        assert_one_line_error(code, err, "no images")

    def test_unknown_config_key(self, tmp_path, capsys):
        bad = tmp_path / "bad.yaml"
        bad.write_text("policy: {bogus: 1}\n")
        code, err = run_detect(["--config", bad, "--out", tmp_path / "out"], capsys)
        line = assert_one_line_error(code, err, "policy.bogus")
        assert "min_inliers" in line  # the allowed keys are named

    def test_missing_config_file(self, tmp_path, capsys):
        code, err = run_detect(["--config", tmp_path / "nope.yaml", "--out", tmp_path / "out"], capsys)
        assert_one_line_error(code, err, "nope.yaml")

    def test_truncated_database(self, tmp_path, capsys, sift_features):
        out = tmp_path / "out"
        out.mkdir()
        db_path = out / "keyframes.h5"
        with KeyframeDatabase(db_path, {}) as db:
            for i in range(3):
                db.append(KeyframeRecord(i, np.zeros(4096, np.float32), sift_features(5)))
        data = db_path.read_bytes()
        db_path.write_bytes(data[: len(data) // 2])
        before = db_path.read_bytes()
        code, err = run_detect(["--out", out], capsys)
        assert_one_line_error(code, err, "keyframes.h5", "is damaged (truncated or corrupt")
        assert db_path.read_bytes() == before

    def test_garbage_weights(self, tmp_path, capsys, copy_sample_frames):
        copy_sample_frames([0, 1], tmp_path / "imgs")
        (tmp_path / "w.pt").write_bytes(b"not a checkpoint" * 10)
        code, err = run_detect([tmp_path / "imgs", "--weights", tmp_path / "w.pt", "--out", tmp_path / "out"],
                               capsys)
        assert_one_line_error(code, err, "w.pt")

    def test_console_script_subprocess(self, tmp_path):
        bad = tmp_path / "bad.yaml"
        bad.write_text("policy: {bogus: 1}\n")
        proc = subprocess.run([sys.executable, "-m", "cae_lcd.cli.main", "detect", "--config", str(bad), "--out",
                               str(tmp_path / "out"), "--no-progress"], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2
        assert "Traceback" not in proc.stderr
        errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and "policy.bogus" in errors[0]


class TestDetectMethod:
    def test_mild_writes_the_same_run_folder(self, sample_dir, tmp_path, capsys):
        out = tmp_path / "mild"
        code, err = run_detect([sample_dir, "--method", "mild", "--out", out], capsys)
        assert code == 0, err
        assert {p.name for p in out.iterdir()} >= {"loops.csv", "candidates.csv", "keyframes.h5", "conf.yaml",
                                                   "summary.json"}
        assert read_csv(out / "loops.csv")[0][:2] == ["query", "match"]
        conf = yaml.safe_load((out / "conf.yaml").read_text())
        assert conf["descriptor"]["name"] == "mild" and conf["temporal"]["name"] == "bayes"
        summary = json.loads((out / "summary.json").read_text())
        assert summary["loops"] >= 30 and summary["ground_truth"]["precision"] >= 0.9  # measured: 35 loops, 1.000
        assert summary["calibration"] is None
        with KeyframeDatabase(out / "keyframes.h5", mode="r") as db:
            rec = next(iter(db))
        assert rec.code.dtype == np.uint8 and rec.code.shape[1] == 32  # the ORB descriptors the hash is rebuilt from

    def test_calibration_needs_a_cosine_descriptor(self, sample_dir, tmp_path, capsys):
        cfg = tmp_path / "c.yaml"
        cfg.write_text("descriptor:\n  name: mild\n")
        code, err = run_detect([sample_dir, "--config", cfg, "--out", tmp_path / "o"], capsys)
        assert_one_line_error(code, err, "calibration.enabled", "'mild'")
        assert not (tmp_path / "o").exists()
        code = main(["calibrate", str(sample_dir), "--method", "mild", "--out", str(tmp_path / "o2")])
        assert_one_line_error(code, capsys.readouterr().err, "not calibrated", "--method mild")

    def test_unknown_method(self, sample_dir, tmp_path, capsys):
        assert main(["detect", str(sample_dir), "--method", "fabmap", "--out", str(tmp_path / "o")]) == 2
        assert "invalid choice: 'fabmap'" in capsys.readouterr().err and not (tmp_path / "o").exists()


class TestCalibrateCommand:
    def test_calibrate_then_detect_uses_it(self, sample_dir, tmp_path, caplog):
        import logging
        caplog.set_level(logging.INFO)
        out = tmp_path / "run"
        assert main(["calibrate", str(sample_dir), "--out", str(out), "--no-progress"]) == 0
        assert (out / "calibration.h5").is_file() and not (out / "keyframes.h5").exists()
        assert any("accept:" in r.getMessage() for r in caplog.records)  # what it chose, and why
        before = (out / "calibration.h5").read_bytes()
        caplog.clear()
        assert main(["detect", str(sample_dir), "--out", str(out), "--lookahead", "--no-progress"]) == 0
        assert any("using the calibration" in r.getMessage() for r in caplog.records)
        assert (out / "calibration.h5").read_bytes() == before
        summary = json.loads((out / "summary.json").read_text())
        assert summary["ground_truth"]["precision"] == 1.0 and summary["loops"] > 0

    def test_bad_path_one_line(self, tmp_path, capsys):
        code = main(["calibrate", str(tmp_path / "missing"), "--out", str(tmp_path / "o")])
        err = capsys.readouterr().err
        assert code == 2 and err.startswith("error: ") and "Traceback" not in err
        assert not (tmp_path / "o").exists()


class TestCameraOptions:
    """``--intrinsics`` and ``--camera-info``: a plain folder (no calib.txt) gets the essential matrix and loop
    edges; a bad camera is one error before anything is written."""

    def test_intrinsics_give_a_plain_folder_its_edges(self, tmp_path, copy_sample_frames, cli_sample_run, sample_K):
        from retrieval.run_folder import RunFolder

        folder = tmp_path / "plain"
        copy_sample_frames(range(100), folder)
        out = tmp_path / "run"
        out.mkdir()
        shutil.copyfile(RunFolder(cli_sample_run[1]).calibration, RunFolder(out).calibration)  # same pixels
        fx, fy, cx, cy = sample_K[0, 0], sample_K[1, 1], sample_K[0, 2], sample_K[1, 2]
        assert main(["detect", str(folder), "--out", str(out), "--no-progress",
                     "--intrinsics", f"{fx},{fy},{cx},{cy}"]) == 0
        run = RunFolder(out)
        assert len(run.read_edges()) == len(run.read_loops()) > 0
        summary = json.loads(run.summary.read_text())
        assert np.allclose(summary["camera"]["K"], sample_K) and summary["camera"]["distortion_model"] == "none"

    @pytest.mark.parametrize("args, message", [
        (["--intrinsics", "1,2,3"], "--intrinsics must be four numbers"),
        (["--camera-info", "missing.yaml"], "cannot read camera file"),
        (["--camera-info", "{bad}"], "takes 4 coefficients"),
        (["--config", "{badconf}"], "takes 4 coefficients"),  # the conf's own check, before anything is written
        # the sample's camera has no pose on a body (no T_BS): edges cannot be put in the body's frame
        (["--edge-frame", "body"], "--edge-frame body: the camera's pose on the body is not known"),
        (["--edge-frame", "body", "--camera-info", "{bad}"], "takes 4 coefficients"),
    ])
    def test_a_bad_camera_is_one_error_and_nothing_is_written(self, tmp_path, args, message, capsys):
        bad = tmp_path / "bad.yaml"
        bad.write_text("intrinsics: [1, 2, 3, 4]\ndistortion_model: equidistant\ndistortion_coefficients: [1]\n")
        badconf = tmp_path / "conf.yaml"
        badconf.write_text("geometry:\n  distortion_model: equidistant\n  distortion_coefficients: [0.1]\n")
        args = [a.replace("{bad}", str(bad)).replace("{badconf}", str(badconf))
                .replace("missing.yaml", str(tmp_path / "missing.yaml")) for a in args]
        out = tmp_path / "run"
        assert main(["detect", "--out", str(out), "--no-progress", *args]) != 0
        assert message in capsys.readouterr().err and not out.exists()

    def test_metric_edges_from_the_sequence_poses(self, tmp_path, cli_sample_run, sample_poses):
        from retrieval.run_folder import RunFolder

        out = tmp_path / "run"
        out.mkdir()
        shutil.copyfile(RunFolder(cli_sample_run[1]).calibration, RunFolder(out).calibration)
        assert main(["detect", "--out", str(out), "--no-progress", "--metric-edges"]) == 0
        edges = RunFolder(out).read_edge_list()
        assert edges and all(e.metric for e in edges)
        for e in edges:
            assert np.linalg.norm(e.t) == pytest.approx(np.linalg.norm(sample_poses[e.query][:, 3]
                                                                       - sample_poses[e.match][:, 3]), rel=1e-6)
        assert json.loads(RunFolder(out).summary.read_text())["metric_edges"] == len(edges)


class TestDetectOnline:
    """``cae-lcd detect`` by default runs the online path (``calibration.online``): the algorithm the API streams, its
    state kept in the keyframe store; ``--lookahead`` keeps the look-ahead calibration (``calibration.online: false``).
    On the sample with a window of 20 frames (the default 50 leaves the sample's revisit inside the warm-up)."""

    CONF = {"search": {"exclude_recent": 20}}

    def test_default_equals_the_api_stream_and_resumes_after_a_kill(self, tmp_path, capsys, sample_seq, sample_image,
                                                                    encoder):
        from retrieval.detector import LoopDetector

        cfg = tmp_path / "w20.yaml"
        cfg.write_text(yaml.safe_dump({**self.CONF, "runtime": {"flush_every": 30}}))
        run = tmp_path / "run"
        code, err = run_detect(["--out", run, "--config", cfg], capsys)
        assert code == 0, err
        with open(run / "loops.csv") as f:
            written = {(int(r["query"]), int(r["match"])) for r in csv.DictReader(f)}
        api = {}
        with LoopDetector(self.CONF, K=sample_seq.K, encoder=encoder) as det:
            for i in range(len(sample_seq)):
                res = det.process(sample_image(i), i)
                api.update({i: res.loop.frame_id} if res.loop is not None else {})
                api.update({q: c.frame_id for q, c in res.confirmed})
        assert written == set(api.items()) and len(written) >= 45  # measured: 49, precision 1.000, recall 0.980
        summary = json.loads((run / "summary.json").read_text())
        assert summary["calibration"]["online"] and not (run / "calibration.h5").exists()
        assert 0 < summary["seconds"]["calibration_online"] < summary["seconds"]["frames"]  # refits inside the frames
        assert summary["loop_edges"] > 0 and summary["seconds"]["loop_edges"] > 0  # the edges' own time, apart
        assert summary["confirmed"] > 0  # the loops the refit at 80 keyframes found late, written as delayed loops
        before = read_csv(run / "loops.csv")
        with h5py.File(run / "keyframes.h5", "a") as f:  # killed after frame 59: later blocks never committed
            assert f["blocks/end"][:4].tolist() == [30, 60, 90, 100]
            f.attrs["committed"] = 60
        code, err = run_detect(["--out", run, "--config", cfg], capsys)
        assert code == 0, err
        assert json.loads((run / "summary.json").read_text())["resumed_at"] == 60
        assert read_csv(run / "loops.csv") == before

    def test_the_progress_counts_the_delayed_loops(self, tmp_path, caplog):
        """With the default window the sample's 100 frames are all warm-up: every loop is found by the fit at its
        last frame and reported as a delayed loop; the progress line counts them (it said ``loops=0`` before)."""
        from retrieval.detect import main as detect

        caplog.set_level(logging.INFO, "cae_lcd.progress")
        summary = detect(None, tmp_path / "run", {}, progress=True)
        lines = [r.getMessage() for r in caplog.records if r.name == "cae_lcd.progress"]
        assert summary["loops"] >= 45 and lines and f"loops={summary['loops']}," in lines[-1], lines[-1:]

    def test_lookahead_option(self, tmp_path, capsys):
        cfg = tmp_path / "w20.yaml"
        cfg.write_text(yaml.safe_dump(self.CONF))
        code, err = run_detect(["--out", tmp_path / "run", "--config", cfg, "--lookahead"], capsys)
        assert code == 0, err
        summary = json.loads((tmp_path / "run" / "summary.json").read_text())
        assert summary["calibration"]["online"] is False and (tmp_path / "run" / "calibration.h5").is_file()
        assert yaml.safe_load((tmp_path / "run" / "conf.yaml").read_text())["calibration"]["online"] is False
