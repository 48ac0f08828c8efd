"""retrieval.calibrate: thresholds chosen from the sequence itself, on the code path users run (``detect``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cae_lcd.core.errors import ConfigError, DatabaseError
from cae_lcd.evaluation.ground_truth import load_ground_truth
from cae_lcd.evaluation.metrics import precision_recall
from retrieval.calibrate import Calibration, calibrated_features, calibration_frames
from retrieval.decision import gaussian_log10_sf
from retrieval.detect import main as detect
from retrieval.run_folder import RunFolder

LOOKAHEAD = {"calibration": {"online": False}}  # detect --lookahead: the calibration pass these tests are about (the
#                                                default detect calibrates on the stream: tests/retrieval/test_online.py)


@pytest.fixture(scope="module")
def kitti_runs(kitti_sequences, tmp_path_factory):
    """``detect`` with the default conf (calibration included) on 00, 07 and 90: run folder by name."""
    runs = {}
    for name in ("00", "07", "90"):
        out = tmp_path_factory.mktemp(f"run{name}")
        detect(kitti_sequences / name, out, LOOKAHEAD, progress=False)
        runs[name] = RunFolder(out)
    return runs


class TestCalibrateOnKitti:
    @pytest.mark.parametrize("name", ["00", "07"])
    def test_no_false_loop_without_revisit(self, kitti_runs, name):
        assert len(kitti_runs[name].read_loops()) == 0

    def test_true_loops_accepted_on_revisit(self, kitti_runs, kitti_sequences):
        run = kitti_runs["90"]
        truth = load_ground_truth(kitti_sequences / "90" / "loops.txt")
        pr = precision_recall(run.read_loops()[:, :2].astype(np.int64), truth.pairs)
        assert pr.precision == 1.0 and pr.recall >= 0.95

    def test_saved_and_explained(self, kitti_runs):
        cal = Calibration.load(kitti_runs["00"].calibration)
        assert cal.whitening is not None and cal.inlier_null and cal.score_null
        assert any(line.startswith("accept:") for line in cal.notes)
        summary = kitti_runs["00"].read_summary()
        assert summary["calibration"]["verification"] is True

    def test_resume_reuses_the_calibration(self, kitti_runs, kitti_sequences):
        run = kitti_runs["07"]
        before = run.calibration.read_bytes()
        detect(kitti_sequences / "07", run.root, LOOKAHEAD, progress=False)  # everything already done: tables rewritten
        assert run.calibration.read_bytes() == before and len(run.read_loops()) == 0


class TestCalibrationMath:
    def cal(self, verification: bool = True) -> Calibration:
        inl = {"u": 10.0, "beta": 2.0, "floor": 12.0, "samples": 100.0} if verification else {}
        return Calibration(score_null={"median": 0.0, "sigma": 0.01, "samples": 100.0}, inlier_null=inl,
                           tests={"score": 1e4, "inliers": 1e3}, expected_false_loops=0.1)

    def test_score_path_threshold_meets_the_target(self):
        cal = self.cal(verification=False)
        t = cal.thresholds()
        assert cal.path == "score" and t["inliers"] is None
        assert cal.confidence(t["score"], -1) >= cal.accept_at > cal.confidence(t["score"] - 1e-3, -1)
        # NFA = tests * P(null >= threshold) <= expected_false_loops / 2
        assert 1e4 * 0.5 * math.erfc(t["score"] / 0.01 / math.sqrt(2)) <= 0.05 + 1e-9

    def test_inlier_path_decides_where_features_verify(self):
        cal = self.cal()
        t = cal.thresholds()
        assert cal.path == "inliers" and t["score"] is None and t["inliers"] >= 12
        assert cal.confidence(0.0, t["inliers"]) >= cal.accept_at > cal.confidence(0.99, t["inliers"] - 1)
        # NFA = tests * 0.5 * exp(-(x - u) / beta) <= 0.05 (the hard-negative tail above its median u)
        assert 1e3 * 0.5 * math.exp(-(t["inliers"] - 10.0) / 2.0) <= 0.05

    def test_more_tests_need_more(self):
        for verification, key in ((False, "score"), (True, "inliers")):
            a, b = self.cal(verification), self.cal(verification)
            b.tests = {"score": 1e6, "inliers": 1e5}
            assert b.thresholds()[key] > a.thresholds()[key]

    @pytest.mark.parametrize("verification", [False, True])
    @pytest.mark.parametrize("empirical", [False, True])
    def test_candidates_at_once_are_each_ones_own(self, verification, empirical):
        """``Calibration.confidences`` (a frame's candidates, a replay's thousands, in one call) against
        ``confidence`` one candidate at a time (the same values bit for bit) and against the rule written out (brute
        force), on both paths, with the model tails (a calibration made by hand) and the measured ones; NaN scores,
        unverified (-1) and under-the-floor counts."""
        rng = np.random.default_rng(3)
        cal = self.cal(verification)
        if empirical:
            cal.score_null["empirical"] = 1.0
            cal.samples["score_null"] = rng.normal(0.0, 0.01, 999)
            if verification:
                cal.inlier_null["empirical"] = 1.0
                cal.samples["hard_inliers"] = rng.integers(0, 30, 700).astype(np.float64)
        scores = np.r_[rng.normal(0.0, 0.02, 200), np.nan, 0.5]
        inliers = np.r_[rng.integers(-1, 60, 200), -1, 11]
        one = [cal.confidence(s, i) for s, i in zip(scores.tolist(), inliers.tolist())]
        assert np.array_equal(cal.confidences(scores, inliers), np.array(one), equal_nan=True)
        assert np.isfinite(one).sum() > 50 and np.isinf(one).any() == verification  # both kinds of values

        def log10_p(x: float, null: np.ndarray | None, model: float) -> float:  # the null's P(X >= x), as promised
            if null is None:
                return model
            return 0.0 if np.isnan(x) or x <= np.median(null) else math.log10((np.sum(null >= x) + 1) / (len(null) + 1))

        want = []
        for s, i in zip(scores.tolist(), inliers.tolist()):
            if verification:
                model = 0.0 if i <= 10 else math.log10(0.5) - (i - 10.0) / 2.0 / math.log(10)
                want.append(-math.inf if i < 12 else -(3.0 + log10_p(i, cal.samples.get("hard_inliers"), model)))
            else:
                want.append(-(4.0 + log10_p(s, cal.samples.get("score_null"), gaussian_log10_sf(s / 0.01))))
        np.testing.assert_allclose(one, want, rtol=1e-9, atol=1e-9)  # NaN where the Gaussian reads a NaN score
        assert cal.confidences(np.zeros(0), np.zeros(0, np.int64)).shape == (0,)

    def test_off_paths(self):
        cal = Calibration()
        assert cal.thresholds() == {"score": None, "inliers": None}
        assert cal.score_confidence(1.0) == -math.inf and cal.inlier_confidence(500) == -math.inf

    def test_file_round_trip(self, tmp_path):
        cal = self.cal()
        cal.notes = ["a", "b"]
        cal.save(tmp_path / "c.h5")
        back = Calibration.load(tmp_path / "c.h5")
        assert back.identity() == cal.identity() and back.notes == ["a", "b"] and back.features == {}
        cal.features = {"name": "sift", "resize_max": 384}
        cal.save(tmp_path / "c.h5")
        again = Calibration.load(tmp_path / "c.h5")
        assert again.features == cal.features and again.identity() == cal.identity() != back.identity()

    def test_older_format_refused(self, tmp_path):
        """A calibration.h5 of format 2 does not say which local features its thresholds were calibrated on."""
        import h5py

        self.cal().save(tmp_path / "c.h5")
        with h5py.File(tmp_path / "c.h5", "a") as h5:
            h5.attrs["format_version"] = 2
        with pytest.raises(ConfigError, match="format_version 2.*calibrate again"):
            Calibration.load(tmp_path / "c.h5")

    def test_damaged_file(self, tmp_path):
        (tmp_path / "c.h5").write_bytes(b"not hdf5")
        with pytest.raises(DatabaseError, match="damaged"):
            Calibration.load(tmp_path / "c.h5")


class TestCalibratedFeatures:
    """A calibrated run extracts its local features at ``calibration.features_px`` (the calibration's and the run's),
    the fixed policy at ``features.resize_max``; a calibration made on other features is refused."""

    def test_the_rule(self):
        from retrieval.detector import resolve_conf

        conf = resolve_conf({})
        assert calibrated_features(conf)["resize_max"] == 384 and conf["features"]["resize_max"] == 512
        assert calibrated_features(resolve_conf({"calibration": {"features_px": None}}))["resize_max"] == 512
        assert calibrated_features(resolve_conf({"features": {"resize_max": None}}))["resize_max"] is None
        assert calibrated_features(resolve_conf({"features": {"name": "orb"}}))["resize_max"] is None  # full size

    def test_recorded_and_checked(self, kitti_runs, encoder):
        from retrieval.detector import LoopDetector

        cal = Calibration.load(kitti_runs["00"].calibration)
        assert cal.features["resize_max"] == 384
        with LoopDetector(calibration=cal, encoder=encoder) as det, \
                LoopDetector({"calibration": {"online": False}}, encoder=encoder) as fixed, \
                LoopDetector(encoder=encoder) as online:  # the stream calibrates itself: its features are those
            assert det.extractor.conf == cal.features and fixed.extractor.conf["resize_max"] == 512
            assert online.extractor.conf == cal.features
        with pytest.raises(ConfigError, match="calibrate again"):
            LoopDetector({"calibration": {"features_px": None}}, calibration=cal, encoder=encoder)
        with LoopDetector({"calibration": {"enabled": False}}, calibration=cal, encoder=encoder) as det:
            assert det.calibration is None and det.extractor.conf["resize_max"] == 512  # the fixed policy


class TestCalibrationFrames:
    def test_all_when_short(self):
        assert list(calibration_frames(100, 50, 10, 2000)) == list(range(100))

    def test_blocks_when_long(self):
        picks = calibration_frames(100_000, 50, 10, 2000)
        assert len(picks) <= 2000 and picks[0] == 0 and picks[-1] == 99_999
        assert np.all(np.diff(picks)[:50] == 1)  # contiguous blocks: far-side pairs exist inside them


class TestCalibrateRefuses:
    def test_short_exclusion(self, sample_dir):
        from retrieval.detect import calibrate_sequence
        from retrieval.sequences import open_sequence
        with pytest.raises(ConfigError, match="exclude_recent"):
            calibrate_sequence(open_sequence(sample_dir), {"search": {"exclude_recent": 2}}, progress=False)


class TestShrunkSample:
    """The bundled sample at 160x120 and 64x32 (``bench.camera.shrunk_sample``), default config."""

    @pytest.mark.parametrize("size,min_recall", [((160, 120), 0.5), ((64, 32), 0.5)])  # measured 1.0 and 0.98
    def test_precision_one(self, tmp_path_factory, size, min_recall):
        from bench.camera import shrunk_sample
        root = tmp_path_factory.mktemp(f"s{size[0]}")
        seq = shrunk_sample(root / "seq", size)
        summary = detect(seq, root / "run", LOOKAHEAD, progress=False)
        truth = load_ground_truth(seq / "loops.txt")
        pr = precision_recall(RunFolder(root / "run").read_loops()[:, :2].astype(np.int64), truth.pairs)
        assert pr.precision == 1.0 and pr.recall >= min_recall
        if size == (64, 32):  # too few SIFT keypoints at 64x32: loops rest on the code and temporal consistency
            assert summary["calibration"]["verification"] is False


class TestCalibrationBelongsToItsWeights:
    def test_other_weights_refused(self, sample_dir, tmp_path, encoder):
        from cae.weights import save_checkpoint
        from retrieval.detect import calibrate_sequence
        from retrieval.sequences import open_sequence
        cal = calibrate_sequence(open_sequence(sample_dir), {}, progress=False)
        assert cal.descriptor == encoder.identity
        cal.descriptor = "0123456789abcdef"  # as if made with other weights
        (tmp_path / "run").mkdir()
        cal.save(tmp_path / "run" / "calibration.h5")
        with pytest.raises(ConfigError, match="other weights"):
            detect(sample_dir, tmp_path / "run", LOOKAHEAD, progress=False)
        assert not (tmp_path / "run" / "keyframes.h5").exists()


def test_features_side_by_side_equal_one_after_another(sample_image):
    from retrieval.calibrate import _extract_side_by_side
    from verify.features import SIFT

    images = {i: sample_image(i) for i in (0, 3, 7, 11, 60)}
    got = _extract_side_by_side({"name": "sift"}, images, [0, 3, 7, 11, 60])
    sift = SIFT()
    assert sorted(got) == [0, 3, 7, 11, 60]
    for fid, image in images.items():
        want = sift.extract(image)
        assert np.array_equal(got[fid].keypoints, want.keypoints)
        assert np.array_equal(got[fid].descriptors, want.descriptors)


def test_own_seconds_apart_from_the_runs_work(sample_dir, tmp_path):
    summary = detect(sample_dir, tmp_path / "run", LOOKAHEAD, progress=False)
    sec = summary["seconds"]
    # the calibration's own work (edge ratios, whitening, nulls, verifications, fits) is timed apart from the
    # run's work it does ahead (reading, encoding, local features the run reuses)
    assert sec["calibration_own"] > 0 and sec["calibration_shared"] > 0
    assert sec["calibration_own"] + sec["calibration_shared"] <= sec["calibration"]  # that one adds loading, saving
    # (issue 27: the measured null verifies calibration.null_pairs = 1200 pairs, which on this 100-frame sample costs
    # more than reading and encoding it: no claim on their ratio here; bench.aliasing reports both)
    assert any("its own work" in n and "the run reuses" in n for n in summary["calibration"]["notes"])


def test_verifications_side_by_side_equal_one_after_another(sample_image):
    from retrieval.calibrate import _samples, _Verify
    from retrieval.detector import resolve_conf

    images = {i: sample_image(i) for i in (0, 2, 4, 50, 52, 54, 60)}
    plan = [("hard", [(54, 4), (52, 2), (50, 0)]), ("positive", [(54, 52), (52, 50)]), ("random", [(60, 0)])]
    conf = resolve_conf({})
    got = _samples(plan, _Verify(conf, images, None, {}), False)
    one = _Verify(conf, images, None, {})
    one.prefetch(images)
    for (kind, pairs) in plan:
        assert got[kind] == [[one(q, r) for q, r in pairs]]
    assert got["positive"][0][0] > 20  # real neighbours verify


def test_positives_are_planned_for_one_query_in_positive_every():
    """``_plan``: every sampled query gets its random pair and its two hard sequences (the null the decision reads);
    the positives, which only describe, one query in ``POSITIVE_EVERY`` (each costs the full check)."""
    from retrieval.calibrate import POSITIVE_EVERY, SPAN, _plan
    from retrieval.temporal import CodeTable

    rng = np.random.default_rng(0)
    ids = np.arange(200)
    table = CodeTable.fixed(ids, rng.normal(size=(200, 16)).astype(np.float32))
    window = 50
    null = np.array([(q, r) for q in range(window + 20, 200) for r in range(q - window + 5, q - window // 2)])
    picks = np.arange(window + 20, 200, 2)
    plan = _plan(null, table, picks, 2, window)
    kinds = [name for name, _ in plan]
    assert kinds.count("random") == kinds.count("hard") == kinds.count("hard2") == len(picks)
    assert kinds.count("positive") == -(-len(picks) // POSITIVE_EVERY) and POSITIVE_EVERY > 1
    positives = [pairs for name, pairs in plan if name == "positive"]
    assert [p[0] for p in positives] == [(int(q), int(q) - 2) for q in picks[::POSITIVE_EVERY]]
    assert all(len(p) == SPAN for p in positives)


@pytest.mark.parametrize("K_known", [True, False])
def test_null_counts_under_the_floor_stop_early_and_decide_nothing(sample_image, sample_K, K_known):
    """Null pairs are checked as the run checks its candidates (the same call: the same count, with or without
    intrinsics): under the floor (``calibration.min_inliers``) the pre-check's count stands (cheaper: no mirror test,
    no essential matrix; without intrinsics, MAGSAC's fundamental matrix instead of a RANSAC run to ``max_iters``).
    With intrinsics the pair null then gives every count at or above the floor the same p-value as a null of full
    checks (the essential matrix's inliers are a subset of the fundamental's); without them the pre-check stands for
    the configured estimator under the floor, so null and candidates share one statistic (on the sample two pairs
    read 11 by MAGSAC and 12 by RANSAC: under the floor, counted so on both sides)."""
    from retrieval.calibrate import _Verify
    from retrieval.decision import EmpiricalTail
    from retrieval.detector import resolve_conf
    from verify.verifier import create_verifier

    conf, K = resolve_conf({}), sample_K if K_known else None
    floor, min_matches = conf["calibration"]["min_inliers"], conf["policy"]["min_matches"]
    pairs = [(q, q - d) for q in range(30, 100, 3) for d in (2, 12, 20, 26)]
    images = {f: sample_image(f) for pair in pairs for f in pair}
    early = _Verify(conf, images, K, {})
    early.prefetch(images)
    full = create_verifier(conf["matcher"], conf["geometry"])
    got, want, run = [], [], []
    for q, r in pairs:
        check = full.verify(early.feats[q], [early.feats[r]], K, min_matches, 0, True)[0]
        want.append(max(check.inliers, 0) if check.matches >= min_matches else 0)
        cand = full.verify(early.feats[q], [early.feats[r]], K, min_matches, floor, True)[0]  # as the run checks
        run.append(max(cand.inliers, 0) if cand.matches >= min_matches else 0)
        got.append(early(q, r))
    got, want = np.array(got), np.array(want)
    assert got.tolist() == run
    assert (got != want).any() and (want >= floor).any() and (want < floor).any()  # both sides, and it mattered
    if K_known:
        assert ((got >= floor) == (want >= floor)).all() and (got[want >= floor] == want[want >= floor]).all()
        x = np.arange(floor, want.max() + 2)
        assert np.array_equal(EmpiricalTail(got).log10_sfs(x), EmpiricalTail(want).log10_sfs(x))


class TestStops:
    """Where the camera stood still (Nordland summer: the train waits at frames 206-241), one place weighed once."""

    @staticmethod
    def _summer(nordland_codes, still_cos):
        from retrieval.calibrate import camera_moved

        ids = np.array([i for i in sorted(nordland_codes) if i < 500], np.int64)
        codes = np.stack([nordland_codes[int(i)] for i in ids])
        return ids, codes, camera_moved(codes, still_cos)

    def test_no_null_line_through_a_stop(self, nordland_codes, encoder):
        from retrieval.calibrate import _null_scores
        from retrieval.decision import SPAN
        from retrieval.temporal import CodeTable, create_filter

        ids, codes, moved = self._summer(nordland_codes, encoder.still_cos)
        table = CodeTable(codes.shape[1])
        for fid, code in zip(ids, codes):
            table.add(int(fid), code / np.linalg.norm(code))
        filt = create_filter({"name": "sequence"})
        pairs = {(int(q), int(r)) for q, r, _ in _null_scores(ids, table, filt, 50, moved)}
        stop, back = set(range(206, 242)), SPAN * filt.conf["length"]
        assert (200, 160) in pairs and len(pairs) > 500  # far from the stop: a null pair
        assert (250, 220) not in pairs  # the camera moved between them, but their line runs through the stop
        assert not any({q - t, r - t} <= stop for q, r in pairs for t in range(back))

    def test_far_side_scores_see_the_stop_in_the_raw_codes(self, nordland_codes, encoder):
        """The stream's drift checks (``far_side_scores``) leave out the pairs through a stop as a fit does, from the
        raw codes at the weights' ``still_cos``: read from the whitened codes at the default ``STILL_COS`` (as the
        checks did), most of the stop's frames looked moved and its lines stayed in their null."""
        from cae.weights import STILL_COS
        from cae.whitening import Whitening
        from retrieval.calibrate import far_side_scores
        from retrieval.temporal import CodeTable, create_filter

        ids, codes, moved = self._summer(nordland_codes, encoder.still_cos)
        white = Whitening.fit(codes).transform(codes)
        unit = white / np.linalg.norm(white, axis=1, keepdims=True)
        whitened_moved = np.r_[True, np.einsum("ij,ij->i", unit[1:], unit[:-1]) < STILL_COS]
        at_stop = (ids > 206) & (ids < 242)
        assert (~moved[at_stop]).sum() >= 30 and (~whitened_moved[at_stop]).sum() < 15
        table, filt = CodeTable.fixed(ids, white), create_filter({"name": "sequence"})
        kept = far_side_scores(ids, table, filt, 50, moved)
        assert 500 < len(kept) < len(far_side_scores(ids, table, filt, 50, whitened_moved)) - 100

    def test_null_lines_scored_in_bulk_as_pair_by_pair(self, nordland_codes, encoder, monkeypatch):
        """The far-side lines, scored ``PAIR_CHUNK`` at a time (a chunk of 97 cuts through queries), are the rows the
        definition gives pair by pair: every ``window // 2 <= q - r < window`` of the ids, its line moved apart at
        every step of the frames its fused score reads, its score the filter's on that one pair."""
        from retrieval.calibrate import _null_scores
        from retrieval.decision import SPAN
        from retrieval.temporal import CodeTable, create_filter

        ids, codes, moved = self._summer(nordland_codes, encoder.still_cos)
        ids, codes, moved = ids[::2][:150], codes[::2][:150], moved[::2][:150]  # gaps in the ids: frames not stored
        table = CodeTable(codes.shape[1])
        for fid, code in zip(ids, codes):
            table.add(int(fid), code / np.linalg.norm(code))
        filt, window = create_filter({"name": "sequence"}), 40
        pos = {int(f): int(c) for f, c in zip(ids, np.cumsum(moved))}
        want = []
        for q in ids.tolist():
            for r in range(max(0, q - window + 1), q - window // 2 + 1):
                if r not in pos:
                    continue
                steps = [(q - t, r - t) for t in range(SPAN * filt.conf["length"])]
                if all(b < 0 or a not in pos or b not in pos or pos[a] - pos[b] >= 1 for a, b in steps):
                    want.append((q, r, float(filt.score(np.array([q]), np.array([r]), table)[0])))
        monkeypatch.setattr("retrieval.calibrate.PAIR_CHUNK", 97)
        got = [(int(q), int(r), float(v)) for q, r, v in _null_scores(ids, table, filt, window, moved)]
        assert len(want) > 200 and got == want

    def test_whitening_and_still_cosine(self, nordland_codes, encoder):
        from retrieval.calibrate import _stretch, _whitening
        from retrieval.detector import resolve_conf
        from retrieval.temporal import CodeTable

        ids, codes, moved = self._summer(nordland_codes, encoder.still_cos)  # the shipped weights' own
        notes: list[str] = []
        white = _whitening(resolve_conf({})["whitening"], None, codes, notes, moved)
        assert (~moved).sum() >= 35 and white.fitted_on == moved.sum()  # by default the stop's frames are left out
        assert "stood still left out" in notes[0]
        table = CodeTable(white.dim)
        for fid, code in zip(ids, white.transform(codes)):
            table.add(int(fid), code)
        cal = Calibration()
        _stretch(cal, ids, table, moved, encoder.still_cos)
        adjacent = table.pairs(ids[1:], ids[1:] - 1)
        says_still = adjacent >= cal.fused["still_cos"]
        assert cal.fused["still_cos"] <= encoder.still_cos
        assert says_still[~moved[1:]].all() and says_still[moved[1:]].sum() <= 2  # the raw codes' verdict, but two
        assert any("stood still" in n for n in cal.notes)


class TestScorePathOnNordland:
    """The score path (64x32: nothing to verify) on real Nordland frames, with the alternative shipped weights
    ``cae_places.pt``: summer 0-149 then winter 500-649 (a revisit a season apart). With the first place-term weights
    the Gaussian tail it used to extrapolate accepted winter 568 -> summer 57 (the place is 67-69); the measured null
    accepts none, with those weights and with the ones shipped now."""

    def test_no_false_loop_with_the_places_weights(self, tmp_path):
        from bench.aliasing import plain_folder
        from cae_lcd.evaluation.ground_truth import read_loop_pairs
        from tests.conftest import NORDLAND, REPO

        if not (NORDLAND / "images").is_dir():
            pytest.skip(f"shared Nordland data not found at {NORDLAND}")
        frames = [*range(0, 150), *range(500, 650)]
        folder = plain_folder(tmp_path / "seq", [NORDLAND / "images" / f"{i:06d}.png" for i in frames])
        detect(folder, tmp_path / "run", {"descriptor": {"weights": str(REPO / "cae" / "weights" / "cae_places.pt")},
                                          **LOOKAHEAD}, progress=False)
        run = RunFolder(tmp_path / "run")
        truth = set(map(tuple, read_loop_pairs(NORDLAND / "loops.txt").tolist()))
        loops = [(frames[int(q)], frames[int(r)]) for q, r in run.read_loops()[:, :2]]
        assert [pair for pair in loops if pair not in truth] == []
        assert len(loops) >= 80  # of 150 winter frames, 146 with a true place in the slice
        assert run.read_summary()["calibration"]["verification"] is False  # the score path decided


class TestReversedLines:
    """The score path's long-range null (``_reversed_lines``): lines read backwards between frames far apart."""

    def test_every_far_pair_read_backwards_as_the_definition_gives_it(self, nordland_codes, monkeypatch):
        """On real Nordland codes (a summer and a winter stretch: gaps in the ids, a stop in each), the lines are
        every ``(q, r)`` whose reversed frames over ``SPAN`` windows leave ``window // 2`` moved frames between them
        and pass a frame where the camera stood still on both sides or on neither, ``q >= newest``, each scored as the filter's mean of ``sim(q - i, r + i)`` (missing frames 0); at most
        ``REVERSED_LINES`` of them, a subset; none for a filter that follows reverse revisits, reads one frame a
        window or has no lines."""
        from retrieval.calibrate import camera_moved, _reversed_lines
        from retrieval.decision import SPAN
        from retrieval.temporal import CodeTable, create_filter

        ids = np.array(sorted(nordland_codes), np.int64)
        raw = np.stack([nordland_codes[int(i)] for i in ids])
        codes, moved = raw / np.linalg.norm(raw, axis=1, keepdims=True), camera_moved(raw)
        table = CodeTable.fixed(ids, codes)
        filt, window, newest = create_filter({"name": "sequence", "length": 4}), 20, 200
        reach, off, by_id = SPAN * 4 - 1, int(ids.max()) + 1, dict(zip(ids.tolist(), codes))
        moved_ids, still_ids = ids[moved], ids[~moved]
        assert len(still_ids) > 20  # the stops: a line passes them on both sides or on neither
        want = {}
        for q in ids[ids >= newest].tolist():
            for r in ids.tolist():
                lo, hi = q - reach, r + reach
                if lo < 0 or hi >= off or ((moved_ids > hi) & (moved_ids < lo)).sum() < window // 2:
                    continue
                if ((still_ids >= lo) & (still_ids <= q)).any() != ((still_ids >= r) & (still_ids <= hi)).any():
                    continue
                terms = [by_id[q - i] @ by_id[r + i] if q - i in by_id and r + i in by_id else 0.0 for i in range(4)]
                want[(q, r)] = float(np.mean(terms))
        rows, mirror = _reversed_lines(ids, table, filt, window, moved, newest)
        got = {(int(q) - off, off - 1 - int(r)): s for q, r, s in rows}  # the mirror's ids -> frame ids
        assert len(want) > 1000 and got.keys() == want.keys()
        assert np.allclose([got[k] for k in want], list(want.values()), atol=1e-5)
        back = rows[:, :2] - 4  # both ids back (as ScoreSpans' windows): the query's frame back, the reference's on
        frames = [(int(q) - off, off - 1 - int(r)) for q, r in back]
        expect = [by_id[a] @ by_id[b] if a in by_id and b in by_id else np.nan for a, b in frames]
        assert np.allclose(mirror.pairs(back[:, 0], back[:, 1]), expect, atol=1e-5, equal_nan=True)
        assert np.isfinite(expect).sum() > 800
        monkeypatch.setattr("retrieval.calibrate.REVERSED_LINES", 300)
        some, _ = _reversed_lines(ids, table, filt, window, moved, newest)
        assert len(some) == 300 and {(int(q), int(r)) for q, r, _ in some} <= {(int(q), int(r)) for q, r, _ in rows}
        for conf in ({"name": "sequence", "length": 4, "velocities": [1.0, -1.0]}, {"name": "sequence", "length": 1},
                     {"name": "none"}, {"name": "bayes"}):  # reverse revisits followed, one-frame windows, no lines
            assert len(_reversed_lines(ids, table, create_filter(conf), window, moved, newest)[0]) == 0

    def test_far_look_alikes_join_the_null(self, monkeypatch):
        """Nordland's 1000 real frames (64x32: the score path) under a code that makes stretches far apart look alike
        (the reconstruction-only weights, ``cae_mixed.pt``, reading standardised images they were not trained on: a
        proxy, BENCHMARKS.md): with the far-side pairs alone as the null, summer frames 443 and 449 close on summer 262
        and 268, 181 frames back, where the railway has no revisit (summer is one traversal); with the reversed lines
        joined, no summer frame closes on another, and the summer -> winter revisits are still found (measured: 334 of
        the 500 winter queries; 292 with the score path's lines at 1x, 2x and 3x the map's speed, each counted among
        the tests)."""
        from cae.model import Encoder
        from cae.weights import RECONSTRUCTION_WEIGHTS, load_encoder
        from cae_lcd.core.images import read_image
        from retrieval.calibrate import calibrate
        from retrieval.detector import resolve_conf
        from retrieval.descriptors import create_descriptor
        from retrieval.temporal import CodeTable, create_filter
        from tests.conftest import NORDLAND

        if not (NORDLAND / "images").is_dir():
            pytest.skip(f"shared Nordland data not found at {NORDLAND}")

        proxy = Encoder("standardise").eval()
        proxy.load_state_dict(load_encoder(RECONSTRUCTION_WEIGHTS, "cpu").state_dict())
        images = [read_image(NORDLAND / "images" / f"{i:06d}.png") for i in range(1000)]
        # at the map's speed only, where it was measured (with the default's lines at 0.87x, 1x and 1.15x the
        # far-side pairs alone already refuse these two)
        conf, filt = resolve_conf({"calibration": {"score_speeds": [1.0]}}), create_filter({"name": "sequence"})
        descriptor = create_descriptor({"name": "cae"}, encoder=proxy)
        codes = dict(enumerate(descriptor.encode_batch(images)))
        truth = load_ground_truth(NORDLAND / "loops.txt").pairs
        ids = np.arange(1000)
        q, r = np.meshgrid(ids, ids, indexing="ij")
        far = (q - r >= 50) & (q < 500)
        q_summer, r_summer = q[far], r[far]
        q_true, r_true = truth[:, 0], truth[:, 1]

        def accepted(lines: int) -> tuple[set, int]:
            monkeypatch.setattr("retrieval.calibrate.REVERSED_LINES", lines)
            cal = calibrate(enumerate(images), 1000, conf, descriptor, filt, progress=False, codes=dict(codes))
            table = CodeTable.fixed(ids, cal.whitening.transform(np.stack([codes[i] for i in ids])))
            spans = cal.score_spans(filt)
            summer = spans.span_confidences(q_summer, r_summer, table).max(1) >= cal.accept_at
            found = spans.span_confidences(q_true, r_true, table).max(1) >= cal.accept_at
            return set(zip(q_summer[summer].tolist(), r_summer[summer].tolist())), len(set(q_true[found].tolist()))

        alone, _ = accepted(0)
        joined, revisits = accepted(20_000)
        assert {(443, 262), (449, 268)} <= alone
        assert joined == set() and revisits >= 300
