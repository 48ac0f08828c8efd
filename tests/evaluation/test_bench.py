"""``cae-lcd bench``: the marker section of BENCHMARKS.md, the index-scaling logic, the sq8 index, and one
``--quick`` run end to end."""

import numpy as np
import pytest

from cae.conf import ConfigError
from evaluation.bench import write_section
from evaluation.bench_index import index_scaling, synth_codes
from retrieval import cli
from retrieval.index import INDEXES, brute_force_search, create_index

BEGIN, END = "<!-- bench:begin -->", "<!-- bench:end -->"


def test_write_section_creates_replaces_and_keeps_the_rest(tmp_path):
    path = tmp_path / "BENCHMARKS.md"
    write_section(path, "first")
    text = path.read_text()
    assert text.startswith("# Benchmarks") and f"{BEGIN}\nfirst\n{END}" in text
    path.write_text("intro by hand\n\n" + path.read_text() + "\n## Lead's notes\nkept as is\n")
    write_section(path, "second")
    text = path.read_text()
    assert text.startswith("intro by hand\n") and text.endswith("\n## Lead's notes\nkept as is\n")
    assert "first" not in text and text.count(BEGIN) == text.count(END) == 1 and "second" in text
    write_section(path, "study", "training")  # a second, named section is appended beside the first
    text = path.read_text()
    assert "<!-- bench:training:begin -->\nstudy\n<!-- bench:training:end -->" in text and "second" in text
    path.write_text(f"{BEGIN}\nno end marker\n")
    with pytest.raises(ConfigError, match="unbalanced"):
        write_section(path, "x")


def test_sq8_index_exact_until_trained_then_close_to_exact():
    rng = np.random.default_rng(0)
    base = np.abs(rng.standard_normal((20, 64), dtype=np.float32))
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    x = synth_codes(base, 600, 0.05, rng)
    index = create_index(64, {"name": "sq8", "train_size": 200})
    assert isinstance(index, INDEXES.get("sq8"))
    index.add(x[:100])  # not trained yet: exact float32
    np.testing.assert_array_equal(index.search(x[:5], 4)[1], brute_force_search(x[:5], x[:100], 4)[1])
    assert index.ntotal == 100 and index.bytes_per_code() == 4 * 64
    index.add(x[100:])
    D, I = index.search(x[:20], 10)
    _, I_ref = brute_force_search(x[:20], x, 10)
    assert index.ntotal == 600 and index.bytes_per_code() < 2 * 64
    assert np.array_equal(I[:, 0], np.arange(20))  # each code finds itself first
    assert np.mean([len(set(a) & set(b)) for a, b in zip(I, I_ref)]) >= 8
    empty = create_index(64, {"name": "sq8"}).search(x[:2], 3)
    assert empty[1].shape == (2, 3) and np.all(empty[1] == -1)


def test_index_scaling_skips_with_reasons():
    rng = np.random.default_rng(1)
    base = np.abs(rng.standard_normal((10, 256), dtype=np.float32))
    base /= np.linalg.norm(base, axis=1, keepdims=True)
    mem = 300 * 256 * 4 / 2**30  # flat fits 300 codes, not 600
    res = index_scaling(base, (300, 600), ("flat", "sq8"), n_queries=8, chunk=100, memory_gib=mem, sigma=0.02)
    cells = res["cells"]
    assert cells[("flat", 300)]["recall"] == 1.0 and cells[("flat", 300)]["top1"] == 1.0
    assert "memory budget" in cells[("flat", 600)]["skipped"]
    assert cells[("sq8", 600)]["recall"] > 0.5 and cells[("sq8", 600)]["bytes_per_code"] < 300


def test_bench_quick_end_to_end(tmp_path, capsys):
    out = tmp_path / "BENCHMARKS.md"
    out.write_text(f"# Benchmarks\n\nlead's text before\n\n{BEGIN}\nold tables\n{END}\n\n## After\nlead's text after\n")
    code = cli.main(["bench", "--quick", "--out", str(out), "--run-dir", str(tmp_path / "runs")])
    assert code == 0
    text = out.read_text()
    assert text.startswith("# Benchmarks\n\nlead's text before\n\n") and text.endswith("## After\nlead's text after\n")
    assert "old tables" not in text and text.count(BEGIN) == 1
    inside = text[text.index(BEGIN):text.index(END)]
    for heading in ("ms/frame by stage", "Encoder throughput", "Methods side by side", "Index scaling"):
        assert heading in inside
    for row in ("| end to end |", "| paper (configs/paper.yaml) |", "| default (CAE) |", "| thumbnail", "| bovw",
                "| sq8 | 2k |", "| hnsw | 500 |", "channels_last"):
        assert row in inside
    assert "Quick mode" in inside
    printed = capsys.readouterr().out
    assert "| end to end |" in printed and "Index scaling" in printed
