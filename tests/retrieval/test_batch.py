"""Many sequences in one command on a local Ray: the same loops as each sequence alone, a summary table, resumable."""

from __future__ import annotations

import csv
import shutil
import json

import numpy as np
import pytest
import yaml

from cae_lcd.cli.main import main
from cae_lcd.core.cluster import start_ray
from cae_lcd.core.conf import ConfigError
from retrieval import detect
from retrieval.batch import batch_outs
from retrieval.run_folder import RunFolder

# 16-frame sequences: loops 8 frames apart count; no calibration (the fixed policy: the test is about Ray, not
# about detection, and a calibration per sequence would cost most of its time)
CONF = {"search": {"exclude_recent": 4}, "calibration": {"enabled": False}}


@pytest.fixture(scope="module")
def collection(tmp_path_factory, copy_sample_frames):
    """Two small sequences (sample frames 0-7 + 50-57 and 10-17 + 60-67: each revisits its first half)."""
    root = tmp_path_factory.mktemp("many") / "sequences"
    for name, start in (("a", 0), ("b", 10)):
        copy_sample_frames([*range(start, start + 8), *range(start + 50, start + 58)], root / name)
    (root.parent / "conf.yaml").write_text(yaml.safe_dump(CONF))
    return root


@pytest.fixture
def no_ray(monkeypatch):
    """Ray not installed (``import ray`` fails), and none running in this process (these tests come before the
    module's local Ray)."""
    import sys

    if "ray" in sys.modules and sys.modules["ray"] is not None and sys.modules["ray"].is_initialized():
        pytest.skip("a Ray runs in this process")
    monkeypatch.setitem(sys.modules, "ray", None)


def test_without_workers_no_ray_is_needed(collection, tmp_path, no_ray, caplog):
    """Without --workers or --ray-address the sequences run one after the other in this process: Ray may be
    missing; a folder holding no sequence is named in a warning, one with unreadable frames in another and in
    ``summary.csv``'s ``unreadable`` column."""
    root = tmp_path / "sequences"
    shutil.copytree(collection, root)
    (root / "notes").mkdir()  # holds no sequence
    (root / "b" / "000016.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 50)
    (root / "b" / "000017.png").write_bytes(b"not an image")
    out = tmp_path / "out"
    args = ["detect", str(root), "--out", str(out), "--no-progress", "--config", str(collection.parent / "conf.yaml")]
    assert main(args) == 0
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [(r["status"], r["unreadable"], r["frames"]) for r in rows] == [("ok", "0", "16"), ("ok", "2", "18")]
    messages = [r.getMessage() for r in caplog.records]
    assert any("hold no sequence" in m and "notes" in m for m in messages), messages
    assert any(m.endswith("2 unreadable frame(s) skipped (their run folder's summary.json names them)")
               for m in messages), messages
    assert len(RunFolder(out / "a").read_loops()) > 0


def test_workers_without_ray_writes_nothing(collection, tmp_path, no_ray, capsys):
    out = tmp_path / "out"
    assert main(["detect", str(collection), "--out", str(out), "--workers", "2", "--no-progress"]) == 2
    assert "this needs Ray" in capsys.readouterr().err
    assert not out.exists()


@pytest.fixture(scope="module")
def local_ray():
    """One local Ray for the module (``run_batch`` uses a running Ray and leaves it running; starting one is slow)."""
    ray, started = start_ray(cpus=2)
    yield
    if started:
        ray.shutdown()


def test_two_sequences_on_ray_like_each_alone(collection, tmp_path, local_ray):
    out = tmp_path / "out"
    args = ["detect", str(collection), "--out", str(out), "--workers", "2", "--no-progress",
            "--config", str(collection.parent / "conf.yaml")]
    assert main(args) == 0
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["sequence"] for r in rows] == [str(collection / "a"), str(collection / "b")]
    assert all(r["status"] == "ok" and r["frames"] == "16" for r in rows)
    assert json.loads((out / "summary.json").read_text())["sequences"][1]["out"] == str(out / "b")
    for name in ("a", "b"):
        alone = detect.main(collection / name, tmp_path / f"alone-{name}", CONF, progress=False)
        many = RunFolder(out / name).read_loops()
        assert len(many) == alone["loops"] > 0
        np.testing.assert_array_equal(many, RunFolder(tmp_path / f"alone-{name}").read_loops())
    (out / "b" / "loops.csv").unlink()
    assert main(args) == 0  # resumed: each run folder already holds its frames, the tables are written again
    np.testing.assert_array_equal(RunFolder(out / "b").read_loops(), RunFolder(tmp_path / "alone-b").read_loops())


def test_list_file_and_name_clash(collection, tmp_path, capsys):
    lst = tmp_path / "list.txt"
    lst.write_text(f"# two sequences\n{collection / 'a'}\n{collection / 'a'}\n")
    from retrieval.sequences import find_sequences

    paths = find_sequences(lst)
    assert paths == [collection / "a"] * 2
    with pytest.raises(ConfigError, match="two sequences named 'a'"):
        batch_outs(paths, tmp_path / "out")
    lst.write_text("missing\n")
    assert main(["detect", str(lst), "--out", str(tmp_path / "o")]) == 2
    assert "no such sequence" in capsys.readouterr().err
