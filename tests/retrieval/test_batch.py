"""Many sequences in one command on a local Ray: the same loops as each sequence alone, a summary table, resumable."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from cli.main import main
from core.cluster import start_ray
from core.conf import ConfigError
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
