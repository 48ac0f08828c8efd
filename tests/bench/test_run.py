"""``cae-lcd bench`` (``bench/``, command line in ``cae_lcd/cli/bench.py``): the marker section of BENCHMARKS.md, the
index-scaling logic, the sq8 index, run metrics from a run folder, the stage table, the options, the layering, and
one ``--quick`` run end to end."""

import ast
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from bench.common import run_metrics
from bench.index_scaling import index_scaling, synth_codes
from bench.run import DEFAULT_SECTIONS, write_section
from bench.speed import STAGE_NAMES, stage_table
from cae_lcd.cli.bench import sections_of
from cae_lcd.cli.main import main as cae_lcd
from cae_lcd.core.conf import ConfigError
from cae_lcd.evaluation.metrics import precision_recall
from retrieval.detector import STAGES
from retrieval.index import INDEXES, brute_force_search, create_index
from retrieval.run_folder import RunFolder

BEGIN, END = "<!-- bench:begin -->", "<!-- bench:end -->"
BENCH_DIR = Path(__file__).parents[2] / "bench"


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


def _unit_base(seed, n, d):
    base = np.abs(np.random.default_rng(seed).standard_normal((n, d), dtype=np.float32))
    return base / np.linalg.norm(base, axis=1, keepdims=True)


def test_index_scaling_skips_with_reasons():
    base = _unit_base(1, 10, 256)
    mem = 300 * 256 * 4 / 2**30  # flat fits 300 codes, not 600
    res = index_scaling(base, (300, 600), ("flat", "sq8"), n_queries=8, chunk=100, memory_gib=mem, sigma=0.02)
    cells = res["cells"]
    assert cells[("flat", 300)]["recall"] == 1.0 and cells[("flat", 300)]["top1"] == 1.0
    assert cells[("flat", 300)]["queries"] == 8 and cells[("flat", 300)]["bytes_per_code"] == pytest.approx(256 * 4, rel=0.01)
    assert "memory budget" in cells[("flat", 600)]["skipped"]
    assert cells[("sq8", 600)]["recall"] > 0.5 and cells[("sq8", 600)]["bytes_per_code"] < 300
    assert set(res["exact_sims"]) == {300, 600}
    top1, topk = res["exact_sims"][300]
    assert 0 < topk <= top1 <= 1.0 + 1e-6


def test_index_scaling_stops_when_the_bench_budget_is_spent():
    from bench.common import Budget

    res = index_scaling(_unit_base(2, 10, 64), (200, 400), ("flat",), n_queries=5, chunk=100, budget=Budget(-1.0))
    assert "bench time left" in res["cells"][("flat", 200)]["skipped"]
    assert res["cells"][("flat", 400)]["skipped"] == "skipped (see the size below)" and res["exact_sims"] == {}


def test_run_metrics_operating_point_from_the_run_folder(tmp_path):
    run = RunFolder(tmp_path)
    # query 10 -> 2 (true), 11 -> 5 (false; its true loop is 4), 12: no loop accepted (its true loop is 1)
    # rows: frame id, cosine, matches, inliers, temporal score, confidence
    run.write_tables([(10, np.array([[2, 0.9, 30, 60, 0.9, 6.0], [3, 0.8, 20, 10, 0.8, 1.0]]), 2),
                      (11, np.array([[5, 0.7, 25, 55, 0.7, 5.5]]), 5),
                      (12, np.array([[1, 0.6, 10, 5, 0.6, 0.5]]), -1)])
    run.write_summary({"loops": 2, "ms_per_frame": {"total": {"median": 12.0, "p90": 20.0}}})  # no "ground_truth"
    gt = np.array([[10, 2], [11, 4], [12, 1]])
    m = run_metrics(tmp_path, gt, min_matches=5)
    assert m["loops"] == 2 and m["ms_total"] == 12.0 and m["score"] == "inliers"
    assert (m["precision"], m["true_positives"], m["detections"], m["positives"]) == (0.5, 1, 2, 3)
    assert m["recall"] == pytest.approx(1 / 3)
    assert m == {**m, **precision_recall(np.array([[10, 2], [11, 5]]), gt).as_dict()}
    assert m["r100"] == pytest.approx(1 / 3) and m["t100"] == 60  # 60 inliers (true), then 55 (false)
    assert m["recall_at_k"][1] == pytest.approx(2 / 3)
    assert run_metrics(tmp_path, None, 5) == {"loops": 2, "ms_total": 12.0, "score": "inliers"}


def test_stage_table_labels_every_detector_stage_in_its_order():
    assert set(STAGE_NAMES) == set(STAGES)
    ms = {s: {"median": float(i), "p90": float(i) + 0.5} for i, s in enumerate(reversed(STAGES))}
    table = stage_table({"ms_per_frame": ms, "frames": 3, "keyframes": 2, "wall_s": 1.0, "bytes_per_keyframe": 2048},
                        "620x188")
    rows = [line.split(" | ")[0].lstrip("| ") for line in table.splitlines()[2:2 + len(STAGES)]]
    assert rows == [STAGE_NAMES[s] for s in STAGES]


def test_options_choose_the_sections(tmp_path, capsys):
    def args(**kw):
        return SimpleNamespace(**{"sections": None, "training_study": False, "skip_scale": False, **kw})

    assert sections_of(args()) == DEFAULT_SECTIONS
    assert sections_of(args(skip_scale=True)) == tuple(s for s in DEFAULT_SECTIONS if s != "index")
    assert sections_of(args(sections="stages, index", skip_scale=True)) == ("stages",)
    assert sections_of(args(training_study=True, sections="stages")) == ("training",)
    assert cae_lcd(["bench", "--sections", "stages,nope", "--run-dir", str(tmp_path / "r")]) == 2
    assert "unknown bench section(s) nope" in capsys.readouterr().err
    assert cae_lcd(["bench", "--index-sizes", "10k"]) == 2
    assert "comma-separated integers" in capsys.readouterr().err


def test_bench_never_imports_cli():
    for path in BENCH_DIR.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            assert not any(n == "cae_lcd.cli" or n.startswith("cae_lcd.cli.") for n in names), f"{path.name} imports {names}"


def test_bench_quick_end_to_end(tmp_path, capsys):
    out = tmp_path / "BENCHMARKS.md"
    out.write_text(f"# Benchmarks\n\nlead's text before\n\n{BEGIN}\nold tables\n{END}\n\n## After\nlead's text after\n")
    code = cae_lcd(["bench", "--quick", "--out", str(out), "--run-dir", str(tmp_path / "runs")])
    assert code == 0
    text = out.read_text()
    assert text.startswith("# Benchmarks\n\nlead's text before\n\n") and text.endswith("## After\nlead's text after\n")
    assert "old tables" not in text and text.count(BEGIN) == 1
    inside = text[text.index(BEGIN):text.index(END)]
    for heading in ("ms/frame by stage", "Encoder throughput", "Methods side by side", "Index scaling"):
        assert heading in inside
    for row in ("| end to end |", "| paper (configs/paper.yaml) |", "| default (CAE) |", "| thumbnail", "| bovw",
                "| sq8 | 2k |", "| hnsw | 500 |", "channels_last", "false loops on quick-noloop"):
        assert row in inside
    assert inside.index("| gate (Canny edge ratio) |") < inside.index("| end to end |")
    assert "Quick mode" in inside
    printed = capsys.readouterr().out
    assert "| end to end |" in printed and "Index scaling" in printed


def test_kill_resume_trials_identical(tmp_path):
    """Two SIGKILLs at random moments of a 16-frame run: both resume to the uninterrupted run's tables."""
    from bench.kill_resume import main as kill_resume

    seq = tmp_path / "seq"
    (seq / "image_0").mkdir(parents=True)
    sample = Path(__file__).parents[2] / "retrieval" / "sample"
    for n, i in enumerate([*range(0, 8), *range(50, 58)]):
        shutil.copyfile(sample / "image_0" / f"{i:06d}.jpg", seq / "image_0" / f"{n:06d}.jpg")
    shutil.copyfile(sample / "calib.txt", seq / "calib.txt")
    (tmp_path / "c.yaml").write_text("search: {exclude_recent: 8}\n")
    res = kill_resume(seq, tmp_path / "work", moments=2, seed=1, config=tmp_path / "c.yaml")
    assert res["identical"] == 2, res["failures"]


def test_detect_run_starts_fresh_and_passes_detect_its_options(tmp_path, sample_seq):
    """``bench.common.detect_run``: a run folder left by another run (here a store that is not one) is emptied first,
    so a bench run after the weights changed does not try to resume it, and ``retrieval.detect.main``'s options
    (the camera's intrinsics) reach it."""
    from bench.common import detect_run

    out = tmp_path / "run"
    out.mkdir()
    (out / "keyframes.h5").write_bytes(b"another run's store")
    summary = detect_run(sample_seq, out, {"calibration": {"online": False}}, intrinsics="300,300,310,94")
    assert summary["frames"] == 100 and summary["camera"]["K"][0] == [300.0, 0.0, 310.0]
