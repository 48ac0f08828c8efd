"""``cae-lcd evaluate`` end to end on a real detect run over the bundled sample, plus hand-built runs."""

import csv
import inspect
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.evaluation import evaluate
from cae_lcd.cli import main as cli
from retrieval.detect import SAMPLE_DIR

PNGS = ("pr_curve.png", "trajectory.png", "similarity.png")


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    """One detect run over the bundled sample (100 real frames, 50 queries with a true loop)."""
    from retrieval.detect import main as detect
    out = tmp_path_factory.mktemp("sample") / "run"
    detect(None, out=out, conf={"policy": {"min_inliers": 30}}, progress=False)
    return out


@pytest.fixture(scope="module")
def report(run, tmp_path_factory):
    return evaluate.main(run, SAMPLE_DIR / "loops.txt", out=tmp_path_factory.mktemp("eval"))


def read_rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def independent_counts(run, gt_file=SAMPLE_DIR / "loops.txt"):
    """Precision/recall, Recall@k and max recall at 100 % precision counted with plain Python sets."""
    gt = {tuple(sorted(map(int, line.split()), reverse=True)) for line in Path(gt_file).read_text().split("\n")
          if line.strip()}
    positives = {i for i, _ in gt}
    loops = [(int(r["query"]), int(r["match"])) for r in read_rows(run / "loops.csv")]
    tp = sum(p in gt for p in loops)
    by_query = {}
    for r in read_rows(run / "candidates.csv"):
        by_query.setdefault(int(r["query"]), []).append(
            (int(r["candidate"]), float(r["seq_score"]), float(r["confidence"]), int(r["inliers"])))
    recall_k = {}
    for k in (1, 5, 10):  # the run's ranking: the temporal score
        hits = {q for q, cs in by_query.items()
                if any((q, c) in gt for c, *_ in sorted(cs, key=lambda c: -c[1])[:k])}
        recall_k[str(k)] = len(hits & positives) / len(positives)
    best = {q: max(cs, key=lambda c: (c[2], c[3], c[1])) for q, cs in by_query.items() if cs}  # by confidence
    best = [(c[2], (q, c[0]) in gt) for q, c in best.items()]
    r100 = 0
    for score in sorted({s for s, _ in best}, reverse=True):
        chosen = [ok for s, ok in best if s >= score]
        if not all(chosen):
            break
        r100 = len(chosen) / len(positives)
    return {"tp": tp, "detections": len(loops), "positives": len(positives), "recall_k": recall_k, "r100": r100}


class TestMainOnSample:
    def test_numbers_agree_with_an_independent_count(self, run, report):
        want = independent_counts(run)
        op = report["operating_point"]
        assert (op["true_positives"], op["detections"], op["positives"]) == (want["tp"], want["detections"], 50)
        assert op["precision"] == pytest.approx(want["tp"] / want["detections"])
        assert op["recall"] == pytest.approx(want["tp"] / 50)
        assert report["retrieval"]["recall_at_k"] == pytest.approx(want["recall_k"])
        assert report["pr_curve"]["max_recall_at_100_precision"] == pytest.approx(want["r100"])
        assert 0 <= report["pr_curve"]["auc"] <= max(report["pr_curve"]["recall"]) + 1e-12

    def test_independent_count_with_false_detections(self, run, tmp_path):
        # keep only the true pairs with an even earlier frame: the detector's other loops become false ones
        pairs = [ln for ln in (SAMPLE_DIR / "loops.txt").read_text().splitlines() if int(ln.split()[1]) % 2 == 0]
        (tmp_path / "gt.txt").write_text("\n".join(pairs) + "\n")
        want = independent_counts(run, tmp_path / "gt.txt")
        r = evaluate.main(run, tmp_path / "gt.txt", out=tmp_path)
        op = r["operating_point"]
        assert op["false_positives"] > 0 and op["positives"] == want["positives"]
        assert (op["true_positives"], op["detections"]) == (want["tp"], want["detections"])
        assert op["recall"] == pytest.approx(want["tp"] / want["positives"])
        assert r["retrieval"]["recall_at_k"] == pytest.approx({k: v for k, v in want["recall_k"].items()})
        assert r["pr_curve"]["max_recall_at_100_precision"] == pytest.approx(want["r100"])

    def test_operating_point_lies_on_the_curve(self, run, report):
        pc, op = report["pr_curve"], report["operating_point"]
        accept = json.loads((run / "summary.json").read_text())["calibration"]["accept_at_confidence"]
        k = max(i for i, t in enumerate(pc["thresholds"]) if t >= accept)  # the calibrated confidence the run used
        assert (pc["true_positives"][k], pc["detections"][k]) == (op["true_positives"], op["detections"])

    def test_json_and_pngs_written(self, report):
        out = Path(report["plots"]["pr_curve"]).parent
        on_disk = json.loads((out / "evaluation.json").read_text())
        assert on_disk == json.loads(json.dumps(report)) and on_disk["format_version"] == 1
        assert on_disk["ground_truth"] == {"path": str(SAMPLE_DIR / "loops.txt"), "kind": "pairs", "pairs": 111,
                                           "queries_with_loop": 50, "frames": 100}
        assert report["skipped"] == []
        for name in PNGS:
            assert (out / name).stat().st_size > 5000, name

    def test_poses_ground_truth_gives_the_same_numbers(self, run, report, tmp_path):
        r = evaluate.main(run, SAMPLE_DIR / "poses.txt", out=tmp_path)
        assert r["ground_truth"]["kind"] == "poses" and r["ground_truth"]["pairs"] == 111
        for key in ("operating_point", "pr_curve", "retrieval"):
            assert r[key] == report[key], key

    def test_cosine_sweep(self, run, tmp_path):
        r = evaluate.main(run, SAMPLE_DIR / "loops.txt", out=tmp_path, score="cosine")
        assert r["pr_curve"]["score"] == "cosine" and all(-1 <= t <= 1 for t in r["pr_curve"]["thresholds"])

    def test_loops_csv_alone(self, run, tmp_path):
        shutil.copy(run / "loops.csv", tmp_path / "loops.csv")
        r = evaluate.main(tmp_path / "loops.csv", SAMPLE_DIR / "loops.txt")
        assert r["pr_curve"] is None and r["retrieval"] is None
        assert set(r["skipped"]) == {"pr_curve", "retrieval", "trajectory", "similarity", "loops_montage",
                                     "missed_montage"}  # no summary.json: the frames are not known
        assert (tmp_path / "evaluation.json").is_file() and not any((tmp_path / n).exists() for n in PNGS)
        assert r["operating_point"]["true_positives"] == independent_counts(run)["tp"]
        r = evaluate.main(tmp_path / "loops.csv", SAMPLE_DIR / "poses.txt")  # poses: the trajectory can be drawn
        assert "trajectory" in r["plots"] and (tmp_path / "trajectory.png").is_file()

    def test_poses_that_do_not_fit_the_run(self, run, tmp_path):
        rows = (SAMPLE_DIR / "poses.txt").read_text().splitlines()
        (tmp_path / "poses.txt").write_text("\n".join(rows[:60]) + "\n")
        with pytest.raises(ConfigError, match="60 poses but the run has 100 frames"):
            evaluate.main(run, tmp_path / "poses.txt", out=tmp_path)


class TestCli:
    def test_evaluate_subcommand(self, run, tmp_path, caplog):
        caplog.set_level("INFO")
        assert cli.main(["evaluate", str(run), "--gt", str(SAMPLE_DIR / "loops.txt"), "--out", str(tmp_path)]) == 0
        assert (tmp_path / "evaluation.json").is_file()
        text = caplog.text
        for needle in ("max recall @ 100% precision", "AUC (average precision", "Recall@1 / @5 / @10"):
            assert needle in text

    def test_cli_defaults_equal_api_defaults(self):
        args = cli.build_parser().parse_args(["evaluate", "RUN"])  # --gt is optional: the run's own ground truth
        api = {k: p.default for k, p in inspect.signature(evaluate.main).parameters.items()
               if p.default is not inspect.Parameter.empty}
        assert {k: getattr(args, k) for k in api} == api

    @pytest.mark.parametrize("make, message", [
        (lambda d: d / "missing", "run not found"),
        (lambda d: d, "holds no loops.csv"),
    ])
    def test_bad_run_is_a_one_line_error(self, tmp_path, capsys, make, message):
        assert cli.main(["evaluate", str(make(tmp_path)), "--gt", str(SAMPLE_DIR / "loops.txt")]) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1

    def test_bad_ground_truth_is_a_one_line_error(self, run, tmp_path, capsys):
        assert cli.main(["evaluate", str(run), "--gt", str(run / "conf.yaml"), "--out", str(tmp_path)]) == 2
        assert "not a ground-truth file" in capsys.readouterr().err

    def test_min_gap_s_without_times(self, tmp_path, capsys):
        (tmp_path / "loops.csv").write_text("query,match,score,matches,inliers\n")
        assert cli.main(["evaluate", str(tmp_path), "--gt", str(SAMPLE_DIR / "poses.txt"), "--min-gap-s", "5"]) == 2
        assert "--min-gap-s needs timestamps" in capsys.readouterr().err


class TestHandBuiltRuns:
    def write_run(self, d: Path, loops=(), cands=()):
        d.mkdir(parents=True, exist_ok=True)
        # rows (query, match, cosine, matches, inliers[, accepted]): temporal score = cosine, confidence = inliers
        (d / "loops.csv").write_text("query,match,score,matches,inliers,seq_score,confidence\n" + "".join(
            ",".join(map(str, (*r, r[2], r[4]))) + "\n" for r in loops))
        (d / "candidates.csv").write_text("query,candidate,score,matches,inliers,seq_score,confidence,accepted\n"
                                          + "".join(",".join(map(str, (*r[:5], r[2], r[4], r[5]))) + "\n"
                                                    for r in cands))
        (d / "summary.json").write_text(json.dumps({"frames": 100}))
        return d

    def test_empty_run(self, tmp_path):
        r = evaluate.main(self.write_run(tmp_path / "run"), SAMPLE_DIR / "loops.txt")
        assert r["operating_point"]["precision"] == 1.0 and r["operating_point"]["recall"] == 0.0
        assert r["pr_curve"]["max_recall_at_100_precision"] == 0.0 and r["pr_curve"]["auc"] == 0.0
        assert r["pr_curve"]["thresholds"] == [] and r["retrieval"]["recall_at_k"] == {"1": 0.0, "5": 0.0, "10": 0.0}
        assert (tmp_path / "run" / "pr_curve.png").is_file()

    def test_no_true_loops(self, tmp_path):
        (tmp_path / "gt.txt").write_text("")
        run = self.write_run(tmp_path / "run", [(60, 3, 0.9, 50, 40)], [(60, 3, 0.9, 50, 40, 1)])
        r = evaluate.main(run, tmp_path / "gt.txt")
        assert r["operating_point"]["precision"] == 0.0 and r["operating_point"]["recall"] is None
        assert r["pr_curve"]["auc"] is None and r["retrieval"]["recall_at_k"]["1"] is None

    def test_known_answer(self, tmp_path):
        # sample ground truth: (50, 0) and (51, 0) are true, (52, 30) is not; 50 queries have a loop
        cands = [(50, 0, 0.9, 80, 60, 1), (50, 7, 0.95, 20, 10, 0), (51, 0, 0.8, 50, 40, 1),
                 (52, 30, 0.9, 70, 50, 1)]
        run = self.write_run(tmp_path / "run", [c[:5] for c in cands if c[5]], cands)
        r = evaluate.main(run, SAMPLE_DIR / "loops.txt")
        assert r["operating_point"]["true_positives"] == 2 and r["operating_point"]["false_detections"] == [[52, 30]]
        assert r["pr_curve"]["thresholds"] == [60, 50, 40]
        assert r["pr_curve"]["max_recall_at_100_precision"] == pytest.approx(1 / 50)
        assert r["pr_curve"]["auc"] == pytest.approx(1 / 50 * 1 + 1 / 50 * 2 / 3)
        assert r["retrieval"]["recall_at_k"] == pytest.approx({"1": 1 / 50, "5": 2 / 50, "10": 2 / 50})

    def test_malformed_csv(self, tmp_path):
        (tmp_path / "loops.csv").write_text("query,score\n1,2\n")
        with pytest.raises(ConfigError, match="missing column"):
            evaluate.main(tmp_path, SAMPLE_DIR / "loops.txt")
        (tmp_path / "loops.csv").write_text("query,match,score,matches,inliers\n1,x,0,0,0\n")
        with pytest.raises(ConfigError, match="non-numeric"):
            evaluate.main(tmp_path, SAMPLE_DIR / "loops.txt")

    def test_bad_options(self, tmp_path):
        run = self.write_run(tmp_path / "run")
        with pytest.raises(ConfigError, match="unknown score"):
            evaluate.main(run, SAMPLE_DIR / "loops.txt", score="auc")
        with pytest.raises(ConfigError, match="radius"):
            evaluate.main(run, SAMPLE_DIR / "poses.txt", radius=0)
