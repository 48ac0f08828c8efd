"""The streaming API on the bundled sample: detection quality against ground truth, resume, ids, gate, results."""

import copy
import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError, load_conf_file, merge_conf
from cae_lcd.core.errors import ImageError
from cae_lcd.evaluation.ground_truth import read_loop_pairs
from cae_lcd.evaluation.metrics import precision_recall
from retrieval.database import KeyframeDatabase
from retrieval.detector import Candidate, FrameResult, LoopDetector, resolve_conf

RESUME_AT = 60


@pytest.fixture(scope="module")
def stream_run(tmp_path_factory, sample_seq, sample_image, encoder, detect_conf):
    """All 100 sample frames through ``LoopDetector.process`` with K from calib.txt, interrupted once:
    frames 0..59 into a database, close, a NEW detector on the same database, frames 60..99."""
    db_path = tmp_path_factory.mktemp("stream") / "keyframes.h5"
    seq = sample_seq

    def run(det, frames):
        return [det.process(sample_image(i), i, float(seq.timestamps[i]), seq.poses[i], seq.frames[i].name)
                for i in frames]

    with LoopDetector(detect_conf, K=seq.K, database=db_path, encoder=encoder) as det:
        results = run(det, range(RESUME_AT))
    with LoopDetector(detect_conf, K=seq.K, database=db_path, encoder=encoder) as det:
        next_id = det.next_frame_id
        n_loaded = len(det.places)
        results += run(det, range(RESUME_AT, len(seq)))
    return {"results": results, "next_id": next_id, "n_loaded": n_loaded, "db": db_path}


def loops_of(results):
    return np.array([(r.frame_id, r.loop.frame_id) for r in results if r.loop is not None], np.int64).reshape(-1, 2)


class TestLoopDetector:
    def test_precision_recall_on_sample(self, stream_run, sample_seq):
        loops = loops_of(stream_run["results"])
        pr = precision_recall(loops, read_loop_pairs(sample_seq.ground_truth))
        # measured: 50 loops, all correct, every query with a true loop found
        assert pr.precision == 1.0
        assert pr.recall >= 0.9
        assert pr.detections >= 45

    def test_resume_continues_and_equals_uninterrupted_run(self, stream_run, cli_sample_run):
        assert stream_run["next_id"] == RESUME_AT
        assert stream_run["n_loaded"] == RESUME_AT
        code, out = cli_sample_run
        assert code == 0
        with open(out / "loops.csv") as f:
            cli_loops = {(int(r["query"]), int(r["match"])) for r in csv.DictReader(f)}
        assert len(cli_loops) >= 45
        stream = set(map(tuple, loops_of(stream_run["results"]).tolist()))
        # the CLI run is calibrated: a loop is a run of frames on one offset (issue 27), so it may miss the first
        # frames of the revisit that the stream's fixed policy (one pair of >= 50 inliers) accepts; nothing else
        from retrieval.decision import SPAN

        assert cli_loops <= stream and all(q < 50 + SPAN - 1 for q, _ in stream - cli_loops)
        with KeyframeDatabase(stream_run["db"], mode="r") as db:
            assert len(db) == 100 and db.last_frame_id() == 99
            recs = list(db)
        assert [r.frame_id for r in recs] == list(range(100))
        assert {(r.frame_id, r.loop) for r in recs if r.loop >= 0} == stream  # what the stream accepted, stored

    def test_frame_results(self, stream_run, detect_conf):
        results = stream_run["results"]
        policy = resolve_conf(detect_conf)["policy"]
        assert [r.frame_id for r in results] == list(range(100))
        assert not any(r.gated for r in results)
        for r in results:
            assert isinstance(r, FrameResult)
            assert r.edge_ratio >= 0.04
            assert {"gate", "encode", "search", "features", "verify", "insert", "total"} <= set(r.ms)
            assert len(r.candidates) <= 10
            # frames younger than exclude_recent (50) are never candidates
            assert all(r.frame_id - c.frame_id >= 50 for c in r.candidates)
            scores = [c.seq_score for c in r.candidates]  # hypotheses, best temporal score first
            assert scores == sorted(scores, reverse=True)
            if r.loop is not None:
                assert r.loop in r.candidates
                assert r.loop.matches >= policy["min_matches"] and r.loop.inliers >= policy["min_inliers"]
                assert r.loop.inliers == max(c.inliers for c in r.candidates)
                assert r.R.shape == (3, 3) and r.t.shape == (3,)
                np.testing.assert_allclose(r.R @ r.R.T, np.eye(3), atol=1e-6)
                assert np.linalg.norm(r.t) == pytest.approx(1.0, abs=1e-6)
        assert all(not r.candidates and r.loop is None for r in results[:50])

    def test_a_loops_check_is_kept_for_its_edge(self, encoder, sample_seq, sample_image, detect_conf):
        """``verified_geometry``: the check that found a loop's pose is what the detector keeps for the pair (its
        edge reuses it, ``retrieval.edges.loop_edges``); a pair never verified has none; the oldest go first, and
        by default (``kept_geometries`` 0) none is kept."""
        frames = [sample_image(i) for i in range(60)]
        with LoopDetector(detect_conf, K=sample_seq.K, encoder=encoder, kept_geometries=1000) as det:
            results = [det.process(frames[i], i) for i in range(58)]
            loops = [r for r in results if r.loop is not None]
            assert loops
            for r in loops:
                assert det.verified_geometry(r.frame_id, r.loop.frame_id) is r.verification.geometry
                assert r.verification.geometry.essential is not None
            assert det.verified_geometry(57, 56) is None and det.verified_geometry(5, 55) is None
            kept = len(det._geometries)
        with LoopDetector(detect_conf, K=sample_seq.K, encoder=encoder, kept_geometries=kept) as det:
            for i in range(58):
                det.process(frames[i], i)
            oldest = next(iter(det._geometries))
            last = [r for r in (det.process(frames[i], i) for i in (58, 59)) if r.loop is not None][-1]
            assert len(det._geometries) == kept and det.verified_geometry(*oldest) is None
            assert det.verified_geometry(last.frame_id, last.loop.frame_id) is last.verification.geometry
        with LoopDetector(detect_conf, K=sample_seq.K, encoder=encoder) as det:
            for i in range(58):
                det.process(frames[i], i)
            assert not det._geometries and det.verified_geometry(loops[-1].frame_id, loops[-1].loop.frame_id) is None
        with pytest.raises(ConfigError, match="kept_geometries"):
            LoopDetector(detect_conf, encoder=encoder, kept_geometries=-1)

    def test_to_dict_json(self, stream_run):
        loop_frame = next(r for r in stream_run["results"] if r.loop is not None)
        for r in (stream_run["results"][0], loop_frame):
            d = json.loads(json.dumps(r.to_dict()))
            assert d["frame_id"] == r.frame_id and d["gated"] is False
            assert len(d["candidates"]) == len(r.candidates)
        d = json.loads(json.dumps(loop_frame.to_dict()))
        assert d["loop"] == {"frame_id": loop_frame.loop.frame_id, "score": loop_frame.loop.score,
                             "matches": loop_frame.loop.matches, "inliers": loop_frame.loop.inliers,
                             "seq_score": loop_frame.loop.seq_score, "confidence": loop_frame.loop.confidence}
        np.testing.assert_allclose(np.array(d["R"]), loop_frame.R)
        assert len(d["t"]) == 3
        assert set(d["ms"]) == set(loop_frame.ms)

    def test_frame_ids_must_increase(self, encoder, sample_image):
        with LoopDetector(encoder=encoder) as det:
            assert det.next_frame_id == 0
            assert det.process(sample_image(0), 5).frame_id == 5
            with pytest.raises(ConfigError, match="frame id 3"):
                det.process(sample_image(1), 3)
            with pytest.raises(ConfigError):
                det.process(sample_image(1), 5)
            assert det.next_frame_id == 6
            assert det.process(sample_image(1)).frame_id == 6  # None: one past the previous frame

    @pytest.mark.parametrize("temporal, warned", [({"name": "none"}, True), ({"length": 1}, True), ({}, False)])
    def test_single_frame_decisions_are_said_to_be_uncertified(self, encoder, caplog, temporal, warned):
        # measured (python -m bench.camera): the raw code deciding frame by frame accepts 39 false loops on Nordland
        with caplog.at_level("WARNING", logger="retrieval.detector"):
            LoopDetector({"temporal": temporal}, encoder=encoder).close()
        assert ("not certified without windows of several frames" in caplog.text) is warned

    @pytest.mark.parametrize("velocities, warned", [([1.0, 2.0, 3.0], True), ([1.0, -1.0], False), ([1.0], False)])
    def test_filter_lines_at_several_speeds_are_warned_of(self, encoder, caplog, velocities, warned):
        # measured (bench.aliasing's KITTI 90 at 64x32, --lookahead, velocities [1, 2, 3]): precision 0.775
        with caplog.at_level("WARNING", logger="retrieval.detector"):
            LoopDetector({"temporal": {"velocities": velocities}}, encoder=encoder).close()
        assert ("lines at several speeds" in caplog.text) is warned

    def test_gated_frame(self, encoder, tmp_path):
        grey = np.full((188, 620), 128, np.uint8)
        with LoopDetector(encoder=encoder, database=tmp_path / "kf.h5") as det:
            res = det.process(grey, 0)
            assert res.gated and res.edge_ratio == 0.0
            assert res.candidates == [] and res.loop is None and res.R is None
            assert "encode" not in res.ms
            assert json.loads(json.dumps(res.to_dict()))["gated"] is True
            assert len(det.places) == 0
        with KeyframeDatabase(tmp_path / "kf.h5", mode="r") as db:
            assert len(db) == 0 and db.gated().tolist() == [0] and db.last_frame_id() == 0
        with LoopDetector(encoder=encoder, database=tmp_path / "kf.h5") as det:
            assert det.next_frame_id == 1

    def test_short_sequence_worker_equals_main_thread(self, encoder, sample_image, sample_K):
        """Frames 0, 1, 2 then their revisits 50, 51, 52 (as ids 3, 4, 5), with a short exclusion window; features of
        every frame (not lazy), from the worker thread or the main thread."""
        frames = [0, 1, 2, 50, 51, 52]
        conf = {"search": {"exclude_recent": 3}, "calibration": {"online": False}}  # the fixed policy: 6 frames are
        #                                                                            too few for a stream to calibrate
        out = {}
        for worker in (True, False):
            with LoopDetector({**conf, "runtime": {"feature_worker": worker, "lazy_features": False}}, K=sample_K,
                              encoder=encoder) as det:
                out[worker] = [det.process(sample_image(i)) for i in frames]
        for a, b in zip(out[True], out[False]):
            assert [c.as_row() for c in a.candidates] == [c.as_row() for c in b.candidates]
        loops = {(r.frame_id, r.loop.frame_id) for r in out[True] if r.loop is not None}
        # 50 -> 0, 51 -> 1, 52 -> 2 are true revisits (sample loops.txt)
        assert loops == {(3, 0), (4, 1), (5, 2)}

    def test_config_errors(self, encoder, stream_run):
        with pytest.raises(ConfigError, match="intrinsics"):
            LoopDetector({"geometry": {"model": "essential"}}, K=None, encoder=encoder)
        with pytest.raises(ConfigError, match="policy.bogus"):
            LoopDetector({"policy": {"bogus": 1}}, encoder=encoder)
        before = stream_run["db"].read_bytes()
        with pytest.raises(ConfigError, match="different configuration"):
            LoopDetector({"policy": {"min_inliers": 7}}, database=stream_run["db"], encoder=encoder)
        assert stream_run["db"].read_bytes() == before


class TestFeatureStoreMode:
    def test_database_mode_same_loops_bounded_memory(self, tmp_path, sample_seq, sample_image, encoder, detect_conf,
                                                     stream_run):
        """Features read back from the database (tiny LRU cache) give the same loops as keeping all in memory."""
        conf = {**detect_conf, "runtime": {"features": "database", "feature_cache": 8}}
        seq = sample_seq
        with LoopDetector(conf, K=seq.K, database=tmp_path / "kf.h5", encoder=encoder) as det:
            results = [det.process(sample_image(i), i, float(seq.timestamps[i])) for i in range(RESUME_AT)]
        with LoopDetector(conf, K=seq.K, database=tmp_path / "kf.h5", encoder=encoder) as det:  # resume
            assert len(det.features) == 0 and len(det.places) == RESUME_AT
            results += [det.process(sample_image(i), i, float(seq.timestamps[i])) for i in range(RESUME_AT, len(seq))]
            assert len(det.features) <= 8
        assert np.array_equal(loops_of(results), loops_of(stream_run["results"]))

    def test_database_mode_memory_flat(self, tmp_path, sample_seq, sample_image, encoder):
        """RSS stays flat as keyframes stream into the database (issue 19 measured 5.5 MiB a frame on this path with
        the store of a group per keyframe): three laps of the sample, features read back through a tiny cache. The
        first lap verifies nothing (no revisit yet): the second warms the verification path (its buffers and the
        verify worker's heap, 45-63 MiB in runs of this test), so the measure is the third lap's growth."""
        def rss_mib():
            return int(Path("/proc/self/statm").read_text().split()[1]) * 4096 / 2**20

        n = len(sample_seq)
        conf = {"runtime": {"features": "database", "feature_cache": 8}}
        with LoopDetector(conf, K=sample_seq.K, database=tmp_path / "kf.h5", encoder=encoder) as det:
            rss = []
            for lap in range(3):
                for i in range(n):
                    det.process(sample_image(i), lap * n + i)
                rss.append(rss_mib())
            assert len(det.db) == 3 * n
        assert rss[2] - rss[1] < 24, rss  # a lap of 100 frames: < 0.25 MiB a frame (measured: 0-1 MiB a lap)

    def test_database_mode_needs_a_database(self, encoder):
        with pytest.raises(ConfigError, match="needs a keyframe database"):
            LoopDetector({"runtime": {"features": "database"}}, encoder=encoder)
        with pytest.raises(ConfigError, match="runtime.features"):
            LoopDetector({"runtime": {"features": "disk"}}, encoder=encoder)


class TestSavedIndex:
    def test_resume_takes_the_saved_graph_index_and_equals_uninterrupted_run(self, tmp_path, sample_seq,
                                                                             sample_image, encoder, caplog):
        """A graph index (rebuilt in minutes at a million keyframes) is saved beside the store on close and taken
        back on resume; the resumed run finds what the uninterrupted one did."""
        conf = {"index": {"name": "hnsw"}, "calibration": {"online": False}}  # the fixed policy (online, a resume
        seq = sample_seq                                                     # rebuilds the index in its whitening)

        def run(det, frames):
            return [(r.frame_id, -1 if r.loop is None else r.loop.frame_id)
                    for r in (det.process(sample_image(i), i, float(seq.timestamps[i])) for i in frames)]

        with LoopDetector(conf, K=seq.K, encoder=encoder) as det:
            whole = run(det, range(len(seq)))
        db = tmp_path / "keyframes.h5"
        with LoopDetector(conf, K=seq.K, database=db, encoder=encoder) as det:
            first = run(det, range(RESUME_AT))
        assert (tmp_path / "keyframes.h5.index").is_file()
        with caplog.at_level("INFO", logger="retrieval.detector"):
            with LoopDetector(conf, K=seq.K, database=db, encoder=encoder) as det:
                assert "restored the place index of" in caplog.text
                second = run(det, range(RESUME_AT, len(seq)))
                indexed = det.places.index.frame_ids
                assert (np.diff(indexed) > 0).all() and det.places.index.index.ntotal == len(indexed)
        assert first + second == whole
        assert sum(m >= 0 for _, m in whole) >= 45


class TestCandidate:
    def test_as_row(self):
        assert Candidate(3, 0.5, 10, 7, 0.4, 2.5).as_row() == (3, 0.5, 10, 7, 0.4, 2.5)


REPO = Path(__file__).parents[2]


class TestStandingStill:
    """Uncalibrated (the API's fixed policy, and ``detect`` where the calibration finds no far-side pair: a camera that
    never moves): a camera standing still is not back at a place, and a revisit after a stop is still found."""

    CONF = {"search": {"exclude_recent": 8}, "calibration": {"enabled": False}}

    def run(self, sample_image, encoder, frames, conf=None):
        with LoopDetector(conf or self.CONF, encoder=encoder) as det:
            return loops_of([det.process(sample_image(i), n) for n, i in enumerate(frames)])

    def test_one_frame_repeated_gives_no_loop(self, sample_image, encoder):
        assert len(self.run(sample_image, encoder, [10] * 24)) == 0  # was: frame 8 -> 0, 9 -> 1, ... (16 loops)

    def test_revisit_after_a_stop_found_and_the_stop_is_no_loop(self, sample_image, encoder):
        frames = [*range(0, 8), *[7] * 10, *range(50, 58)]  # move, stand still at frame 7, revisit 0..7
        loops = self.run(sample_image, encoder, frames)
        assert all(n >= 18 for n, _ in loops), loops  # none inside the stop (was: 14 -> 6, 15 -> 7, ...)
        assert len(loops) >= 6 and all(m < 18 for _, m in loops)  # the revisit: 50..57 -> 0..7 (7: its stop)

    def test_off_is_the_literal_rule(self, sample_image, encoder):
        conf = {**self.CONF, "policy": {"still_cos": None}}
        assert len(self.run(sample_image, encoder, [10] * 12, conf)) == 4


class TestResolveConf:
    """``resolve_conf``: registry sections merge onto the named unit's defaults; every value is checked."""

    def test_hnsw_options_allowed_only_for_hnsw(self):
        from retrieval.detector import resolve_conf
        from retrieval.index import HNSWIndex

        conf = resolve_conf({"index": {"name": "hnsw", "m": 16}})
        assert conf["index"] == {**HNSWIndex.default_conf, "m": 16}
        with pytest.raises(ConfigError, match="index.m"):
            resolve_conf({"index": {"name": "flat", "m": 16}})
        with pytest.raises(ConfigError, match="unknown index 'nope'"):
            resolve_conf({"index": {"name": "nope"}})

    def test_defaults_and_unknown_keys(self):
        from retrieval.detector import default_conf, resolve_conf

        before = copy.deepcopy(default_conf)
        conf = resolve_conf({"policy": {"min_inliers": 30}, "features": {"max_features": 123}})
        assert conf["policy"] == {"verify": True, "min_matches": 5, "min_inliers": 30, "min_seq_score": None,
                                  "check_all": False, "still_cos": 0.999}
        from verify.features import SIFT

        assert conf["features"]["max_features"] == 123
        assert conf["features"]["resize_max"] == SIFT.default_conf["resize_max"]  # the rest from SIFT's defaults
        assert default_conf == before
        assert resolve_conf(conf) == conf  # idempotent
        with pytest.raises(ConfigError) as err:
            resolve_conf({"policy": {"bogus": 1}})
        assert "policy.bogus" in str(err.value) and "min_inliers" in str(err.value)

    @pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "configs").glob("*.yaml") if p.name != "train.yaml"))
    def test_detector_presets_resolve(self, name):
        from retrieval.detector import resolve_conf

        user = load_conf_file(REPO / "configs" / name)
        conf = resolve_conf(user)
        for section, values in user.items():
            if isinstance(values, dict):
                for key, value in values.items():
                    assert conf[section][key] == value

    def test_default_preset_equals_code_defaults(self):
        from retrieval.detector import resolve_conf

        path = REPO / "configs" / "default.yaml"
        if not path.is_file():
            pytest.skip("configs/default.yaml not present")
        assert resolve_conf(load_conf_file(path)) == resolve_conf({})

    def test_train_preset_resolves(self):
        from cae.train import default_conf

        user = load_conf_file(REPO / "configs" / "train.yaml")
        assert merge_conf(default_conf, user) == {**default_conf, **user}

    @pytest.mark.parametrize("old", ["encoder", "matching"])
    def test_old_section_names_are_unknown_keys(self, old):
        from retrieval.detector import resolve_conf

        with pytest.raises(ConfigError, match=f"'{old}'"):
            resolve_conf({old: {}})

    @pytest.mark.parametrize("override, key", [
        ({"search": {"k": 0}}, "search.k"), ({"search": {"k": True}}, "search.k"),
        ({"geometry": {"threshold": float("nan")}}, "geometry.threshold"),
        ({"index": {"name": "hnsw", "m": 1}}, "index.m"), ({"runtime": {"features": "disk"}}, "runtime.features"),
        ({"descriptor": {"name": "thumbnail", "width": 1}}, "descriptor.width"),
    ])
    def test_values_checked(self, override, key):
        from retrieval.detector import resolve_conf

        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            resolve_conf(override)


class TestEveryUnitDeclaresItsRules:
    """Every key of every unit's default_conf has a type-and-range rule (a new key without one fails here)."""

    def test_all_registered_units(self):
        from cae_lcd.core.conf import check_conf
        from retrieval.detector import conf_rules, default_conf
        from retrieval.descriptors import DESCRIPTORS
        from retrieval.index import INDEXES
        from verify.features import FEATURES
        from verify.gate import EdgeGate
        from verify.geometry import GeometricVerifier
        from verify.verifier import MATCHERS

        units = [EdgeGate, GeometricVerifier] + [reg.get(n) for reg in (DESCRIPTORS, INDEXES, FEATURES, MATCHERS)
                                                  for n in reg.names()]
        for unit in units:
            check_conf(unit.default_conf, unit.conf_rules, unit.__name__)
            assert set(unit.conf_rules) <= set(unit.default_conf), unit
        for section, rules in conf_rules.items():
            check_conf(default_conf[section], rules, section)


class TestProcessRefusesBadInput:
    """The Python API raises the project's own errors and leaves the detector as it was."""

    @pytest.mark.parametrize("image, error", [
        (None, "numpy array"), ([[1, 2], [3, 4]], "numpy array"), ("000000.png", "read files with"),
        (np.zeros((4, 4), np.uint8), "too small"), (np.zeros((1, 2000), np.uint8), "too small"),
        (np.zeros((50, 60, 2), np.uint8), "unsupported image shape"), (np.zeros((50, 60), np.complex64), "dtype"),
    ], ids=["None", "list", "path", "4x4", "strip", "2-channel", "complex"])
    def test_bad_images(self, encoder, sample_image, tmp_path, image, error):
        with LoopDetector(encoder=encoder, database=tmp_path / "kf.h5") as det:
            det.process(sample_image(0), 0)
            with pytest.raises(ImageError, match=error):
                det.process(image, 1)
            assert det.next_frame_id == 1 and len(det.places) == 1 and len(det.db) == 1
            assert det.process(sample_image(1), 1).frame_id == 1  # the same id is still free

    def test_torch_tensor(self, encoder, sample_image):
        import torch

        with LoopDetector(encoder=encoder) as det:
            with pytest.raises(ImageError, match="got Tensor"):
                det.process(torch.zeros(3, 64, 64))

    @pytest.mark.parametrize("kwargs, error", [
        ({"frame_id": 1.7}, "frame_id must be an integer"), ({"frame_id": "3"}, "frame_id must be an integer"),
        ({"frame_id": True}, "frame_id must be an integer"), ({"pose": np.eye(3)}, "pose must be a finite 3x4"),
        ({"pose": np.full((3, 4), np.nan)}, "NaN or inf"), ({"timestamp": float("nan")}, "timestamp"),
        ({"timestamp": "noon"}, "timestamp"), ({"frame_id": 2**63}, "frame_id must be in"),
        ({"frame_id": -1}, "frame_id must be in"), ({"timestamp": 1e300}, "timestamp"),
    ])
    def test_bad_arguments(self, encoder, sample_image, kwargs, error):
        with LoopDetector(encoder=encoder) as det:
            with pytest.raises(ConfigError, match=error):
                det.process(sample_image(0), **kwargs)
            assert det.next_frame_id == 0 and len(det.places) == 0

    def test_pose_4x4_accepted(self, encoder, sample_image, tmp_path):
        pose = np.eye(4)
        pose[:3, 3] = [1, 2, 3]
        with LoopDetector(encoder=encoder, database=tmp_path / "kf.h5") as det:
            det.process(sample_image(0), 0, pose=pose)
            np.testing.assert_array_equal(next(iter(det.db)).pose, pose[:3])

    @pytest.mark.parametrize("K", [np.eye(2), np.full((3, 3), np.inf), "K", np.zeros((3, 3)), -np.eye(3)])
    def test_bad_intrinsics(self, encoder, K):
        with pytest.raises(ConfigError, match="K must be"):
            LoopDetector(K=K, encoder=encoder)

    def test_process_after_close(self, encoder, sample_image, tmp_path):
        det = LoopDetector(encoder=encoder, database=tmp_path / "kf.h5")
        det.process(sample_image(0), 0)
        det.close()
        with pytest.raises(ConfigError, match="closed"):
            det.process(sample_image(1), 1)
        assert det.next_frame_id == 1 and len(det.places) == 1


class TestGivenDescriptor:
    def test_used_as_given_and_checked(self, encoder):
        from retrieval.descriptors import CAEDescriptor
        d = CAEDescriptor(encoder=encoder)
        with LoopDetector(descriptor=d) as det:
            assert det.descriptor is d  # built once (detect shares the calibration's), not again
        with pytest.raises(ConfigError, match="descriptor must be"):
            LoopDetector({"descriptor": {"name": "thumbnail"}}, descriptor=d)


class TestMildMethod:
    """``LoopDetector`` with MILD's descriptor, hashing and Bayesian filter (``retrieval.methods``)."""

    def test_resumed_run_equals_uninterrupted_run(self, tmp_path, sample_seq, sample_image):
        from retrieval.methods import method_conf

        conf, frames = method_conf("mild"), range(len(sample_seq))
        with LoopDetector(conf, K=sample_seq.K) as det:
            whole = [det.process(sample_image(i), i) for i in frames]
        db = tmp_path / "keyframes.h5"
        with LoopDetector(conf, K=sample_seq.K, database=db) as det:
            parts = [det.process(sample_image(i), i) for i in frames[:RESUME_AT]]
        with LoopDetector(conf, K=sample_seq.K, database=db) as det:  # the filter's state is replayed
            parts += [det.process(sample_image(i), i) for i in frames[RESUME_AT:]]
        rows = np.array([c.as_row() for r in whole for c in r.candidates])
        np.testing.assert_allclose(np.array([c.as_row() for r in parts for c in r.candidates]), rows, rtol=1e-5)
        assert loops_of(parts).tolist() == loops_of(whole).tolist() and len(loops_of(whole)) >= 30
        assert all(r.ms["features"] == 0.0 for r in whole)  # MILD alone verifies nothing: no SIFT extracted

    def test_mild_verify_on_sample(self, tmp_path, sample_seq):
        from retrieval import detect
        from retrieval.methods import method_conf

        detect.main(sample_seq.root, tmp_path / "run", method_conf("mild+verify"), progress=False)
        with open(tmp_path / "run" / "loops.csv") as f:
            loops = np.array([(int(r["query"]), int(r["match"])) for r in csv.DictReader(f)]).reshape(-1, 2)
        pr = precision_recall(loops, read_loop_pairs(sample_seq.ground_truth))
        assert pr.precision == 1.0 and pr.recall >= 0.9  # measured: 1.000 / 1.000


class TestLazyFeatures:
    """Local features only where a candidate could pass (``runtime.lazy_features``), codes given ahead: the same
    results as extracting and encoding every frame as it comes."""

    FRAMES = range(0, 70)  # 50 frames without a candidate, then the start of the revisit

    def run(self, conf, encoder, sample_seq, sample_image, **kwargs):
        conf = {**conf, "calibration": {"online": False}}  # 70 frames: within an online stream's warm-up
        with LoopDetector(conf, K=sample_seq.K, encoder=encoder, **kwargs) as det:
            return [det.process(sample_image(i), i) for i in self.FRAMES]

    def test_lazy_equals_eager(self, encoder, sample_seq, sample_image):
        eager = self.run({"runtime": {"lazy_features": False}}, encoder, sample_seq, sample_image)
        copies = self.run({}, encoder, sample_seq, sample_image)  # lossless copies of the frames kept in memory
        calls = []

        def again(fid):
            calls.append(fid)
            return sample_image(fid)

        source = self.run({}, encoder, sample_seq, sample_image, frame_source=again)
        alone = self.run({"runtime": {"feature_worker": True}}, encoder, sample_seq, sample_image)  # the worker
        serial = self.run({"runtime": {"feature_worker": False, "verify_worker": False}}, encoder, sample_seq,
                          sample_image)  # one thread: features, matching and checks on the caller's
        rows = [[c.as_row() for c in r.candidates] for r in eager]
        assert sum(len(r) for r in rows) > 50 and len(loops_of(eager)) >= 15
        for lazy in (copies, source, alone, serial):
            assert [[c.as_row() for c in r.candidates] for r in lazy] == rows
            assert loops_of(lazy).tolist() == loops_of(eager).tolist()
        assert all(r.ms["features"] > 0 for r in eager)
        assert all(r.ms["features"] == 0 for r in copies[:50])  # no candidate yet: nothing extracted
        assert calls and len(set(calls)) == len(calls)  # frames read again when a candidate needed them, once

    def test_prefetched_features_give_the_same_results(self, encoder, sample_seq, sample_image):
        """``prefetch_features`` of the next two frames before each one (as ``detect`` does), one of them with a
        wrong image under the right id: the same candidates and loops as extracting each frame's when it comes."""
        plain = self.run({}, encoder, sample_seq, sample_image)
        images = {i: sample_image(i) for i in self.FRAMES}
        wrong = 60  # prefetched with another frame's image: process then gets the right one
        started, results = [], []
        with LoopDetector({"calibration": {"online": False}}, K=sample_seq.K, encoder=encoder) as det:
            for i in self.FRAMES:
                for k in (i + 1, i + 2):
                    if k in images:
                        started.append(det.prefetch_features(images[k + 5] if k == wrong else images[k], k))
                results.append(det.process(images[i], i))
            with pytest.raises(ConfigError, match="not after the last frame"):
                det.prefetch_features(images[3], 3)
        assert any(started) and not all(started)  # before the first candidate nothing is wanted ahead
        assert [[c.as_row() for c in r.candidates] for r in results] == \
            [[c.as_row() for c in r.candidates] for r in plain]
        assert loops_of(results).tolist() == loops_of(plain).tolist() and len(loops_of(plain)) >= 15

    def test_given_codes_equal_encoded(self, encoder, sample_seq, sample_image):
        from retrieval.descriptors import create_descriptor

        d = create_descriptor({"name": "cae"}, encoder=encoder)
        images = [sample_image(i) for i in range(0, 100, 9)]
        batch = d.encode_batch(images)
        assert all(np.array_equal(b, d(im)) for b, im in zip(batch, images))  # bit for bit
        with LoopDetector(K=sample_seq.K, descriptor=d) as det:
            det.process(images[0], 0, code=batch[0])
            with pytest.raises(ConfigError, match="code must be"):
                det.process(images[1], 1, code=batch[1][:10])
            assert det.next_frame_id == 1  # refused: nothing changed

    def test_a_small_frame_is_encoded_as_the_weights_read_it(self, encoder, nordland_codes):
        """A 64x32 frame streamed through ``process`` is coded through the weights' ``lowpass`` (the shipped
        weights': 0.6), as ``encode_batch`` and ``encode_images`` code it: one code a frame on every path."""
        from cae_lcd.core.images import read_image
        from retrieval.descriptors import create_descriptor
        from tests.conftest import NORDLAND

        assert encoder.lowpass > 0
        d = create_descriptor({"name": "cae"}, encoder=encoder)
        ids = list(nordland_codes)[:12]
        with LoopDetector(descriptor=d) as det:
            results = [det.process(read_image(NORDLAND / "images" / f"{i:06d}.png"), n) for n, i in enumerate(ids)]
        coded = [(r.code, nordland_codes[i]) for r, i in zip(results, ids) if r.code is not None]
        assert len(coded) >= 6
        for mine, batch in coded:  # the stream keeps its raw codes as float16 (LoopDetector: a refit whitens them)
            np.testing.assert_allclose(mine, batch, rtol=0, atol=2e-4)

    def test_calibrated_verify_gate_keeps_the_loops(self, tmp_path, cli_sample_run, sample_seq):
        """The calibrated run (lazy, gate on, codes and features from the calibration) against every candidate
        verified on every frame's features, with the same calibration: the same loops.csv."""
        import shutil

        from retrieval import detect

        _, out = cli_sample_run
        old = tmp_path / "old"
        old.mkdir()
        shutil.copyfile(out / "calibration.h5", old / "calibration.h5")
        detect.main(sample_seq.root, old, {"search": {"verify_min_z": None}, "runtime": {"lazy_features": False},
                                           "calibration": {"online": False}}, progress=False)
        assert (old / "loops.csv").read_text() == (out / "loops.csv").read_text()
        with open(out / "candidates.csv") as f:
            skipped = sum(int(r["inliers"]) == -1 and int(r["matches"]) == 0 for r in csv.DictReader(f))
        assert skipped > 100  # the gate left most non-loop candidates unverified


class TestStreamStore:
    """A stream (no calibration) into a store: its own whitening fitted on its first keyframes, a grey copy of each
    keyframe whose features were not needed when it came (``runtime.features: image``), a bounded memory; resumed,
    the same tables as uninterrupted."""

    CONF = {"calibration": {"enabled": False}, "whitening": {"stream_fit": 32},
            "runtime": {"features": "image", "feature_cache": 16, "feature_worker": True}}

    def run(self, path, encoder, sample_seq, sample_image, frames, conf=None):
        with LoopDetector(conf or self.CONF, K=sample_seq.K, database=path, encoder=encoder) as det:
            out = [det.process(sample_image(i), i) for i in frames]
            state = {"dim": det.places.dim, "copies": len(det._copies), "kept": len(det.features)}
        return out, state

    def test_resumed_equals_uninterrupted_and_stays_small(self, tmp_path, encoder, sample_seq, sample_image):
        whole, state = self.run(tmp_path / "a.h5", encoder, sample_seq, sample_image, range(100))
        first, _ = self.run(tmp_path / "b.h5", encoder, sample_seq, sample_image, range(RESUME_AT))
        rest, _ = self.run(tmp_path / "b.h5", encoder, sample_seq, sample_image, range(RESUME_AT, 100))
        rows = [[c.as_row() for c in r.candidates] for r in whole]
        assert [[c.as_row() for c in r.candidates] for r in first + rest] == rows
        assert loops_of(first + rest).tolist() == loops_of(whole).tolist()
        pr = precision_recall(loops_of(whole), read_loop_pairs(sample_seq.ground_truth))
        assert pr.precision == 1.0 and pr.detections >= 40
        assert state == {"dim": 8, "copies": 0, "kept": 16}  # whitened (32 codes // 4); features: feature_cache
        with KeyframeDatabase(tmp_path / "b.h5", mode="r") as db:
            assert len(db.features(10)) == 0 and db.has_image(10) and 1000 < len(db.image(10)) < 24 * 1024  # a copy
            assert len(db.features(70)) > 100 and not db.has_image(70) and db.image(70) == b""  # a revisit: features
            codes = dict((fid, code) for fid, code, _, _ in db.search_entries(features=False))
        assert len(codes[0]) == 4096 and len(codes[99]) == 8  # raw until the fit, then whitened

    def test_features_from_the_copy_verify_as_the_frames_do(self, tmp_path, encoder, sample_seq, sample_image):
        """Lossless copies (PNG) give the features of the frames themselves: the candidates of the in-memory stream."""
        conf = merge_conf(self.CONF, {"runtime": {"image_quality": None}}, strict=False)
        stored, _ = self.run(tmp_path / "c.h5", encoder, sample_seq, sample_image, range(70), conf)
        with LoopDetector({**self.CONF, "runtime": {}}, K=sample_seq.K, encoder=encoder) as det:
            memory = [det.process(sample_image(i), i) for i in range(70)]
        assert [[c.as_row() for c in r.candidates] for r in stored] == \
            [[c.as_row() for c in r.candidates] for r in memory]


class TestWhereAVisitEnds:
    def test_the_last_frame_is_placed_by_its_own_pair_not_the_line_past_the_visit(self, kitti_sequences, tmp_path,
                                                                                     encoder):
        """KITTI 90 at 64x32 (the score path) with its second pass seen through a narrower lens (its centre 80 %
        brought back up: a camera that sees a frame ahead): the second pass's line sits one frame ahead of the first
        pass's, and at the first pass's end it runs on into frame 100, the second pass's own start. Streamed through
        the API, every loop must be true; the last frame's was 199 on 100 (its own pair at a whitened cosine of
        -0.21, its window's nine other pairs good) before the frame's own pair placed it among equally confident
        lines one frame apart (``retrieval.detector._placed``)."""
        import cv2

        from bench.augment import narrower
        from retrieval.sequences import open_sequence

        seq = open_sequence(kitti_sequences / "90")
        truth = {tuple(sorted(p)) for p in read_loop_pairs(kitti_sequences / "90" / "loops.txt").tolist()}
        loops = []
        with LoopDetector(encoder=encoder) as det:
            for i in range(len(seq)):
                image = seq.read_frame(i)[0]
                image = narrower(image) if i >= len(seq) // 2 else image
                result = det.process(cv2.resize(image, (64, 32), interpolation=cv2.INTER_AREA), i)
                loops += [(f, cd.frame_id) for f, cd in result.confirmed]
                loops += [(i, result.loop.frame_id)] if result.loop is not None else []
        false = [pair for pair in loops if tuple(sorted(pair)) not in truth]
        assert not false, false
        assert len({q for q, _ in loops}) >= 95  # measured: 100 (every query), 199 on 99
        assert (199, 99) in loops


class TestARevisitAtAnotherSpeed:
    """KITTI 90 with its second pass three times as fast (every third frame from 100): runs of verified frames are
    fused on lines at 1x, 2x and 3x the map's speed (``calibration.speeds``), and the first pass's keyframes that the
    sequence filter's lines carry lag the query while their pairs verify (13-76 inliers, 6-24 m behind, where the
    place holds 110-226); toward the pass's end the place lies inside the exclusion window. Streamed through the
    API, each loop must name the keyframe the query is at (``retrieval.localise``): without the walk 6 of 31 loops
    were 6-16 m off."""

    KEEP = (*range(100), *range(100, 200, 3))

    def stream(self, kitti_sequences, encoder, steps):
        from retrieval.sequences import open_sequence

        seq = open_sequence(kitti_sequences / "90")
        loops, self.unplaced = [], []  # frames without a loop whose stored candidates still pass (a replay's choice)
        with LoopDetector({"search": {"localise_steps": steps}}, encoder=encoder) as det:
            for i, src in enumerate(self.KEEP):
                result = det.process(seq.read_frame(src)[0], i)
                loops += [(self.KEEP[f], self.KEEP[cd.frame_id]) for f, cd in result.confirmed]
                loops += [(src, self.KEEP[result.loop.frame_id])] if result.loop is not None else []
                cal = det.deciding_calibration
                if result.loop is None and cal is not None and \
                        any(cd.confidence >= cal.accept_at for cd in result.candidates):
                    self.unplaced.append(i)
        truth = {tuple(sorted(p)) for p in read_loop_pairs(kitti_sequences / "90" / "loops.txt").tolist()}
        return loops, [pair for pair in loops if tuple(sorted(pair)) not in truth]

    def test_every_loop_names_the_place_the_query_is_at(self, kitti_sequences, encoder):
        loops, false = self.stream(kitti_sequences, encoder, 16)
        assert not false, false
        assert len({q for q, _ in loops}) >= 20  # measured: 26 of the 34 queries (at the map's speed only: 1)
        assert not self.unplaced  # a refused loop vetoes every candidate that passed

    def test_without_the_walk_loops_lag(self, kitti_sequences, encoder):
        _, false = self.stream(kitti_sequences, encoder, 0)
        assert len(false) >= 3, false  # measured: 127 on 24, 145 on 40, 181 on 77 ... 190 on 80


class TestAFasterRevisitOnTheScorePath:
    """KITTI 90 at 64x32 (too few keypoints to verify: the score path decides) with its second pass twice as fast
    (every second frame from 100): its windows lie on a line at 2x the map's speed, which the score path fuses where
    ``calibration.score_speeds`` holds it (``retrieval.decision.ScoreSpans``); at the map's speed only, nothing is
    found."""

    KEEP = (*range(100), *range(100, 200, 2))

    def stream(self, kitti_sequences, encoder, speeds):
        from retrieval.sequences import open_sequence

        seq = open_sequence(kitti_sequences / "90")
        loops = []
        with LoopDetector({"calibration": {"score_speeds": speeds}}, encoder=encoder) as det:
            for i, src in enumerate(self.KEEP):
                image = cv2.resize(seq.read_frame(src)[0], (64, 32), interpolation=cv2.INTER_AREA)
                result = det.process(image, i)
                loops += [(self.KEEP[f], self.KEEP[cd.frame_id]) for f, cd in result.confirmed]
                loops += [(src, self.KEEP[result.loop.frame_id])] if result.loop is not None else []
            assert not det.deciding_calibration.inlier_null  # the score path decided
        truth = {tuple(sorted(p)) for p in read_loop_pairs(kitti_sequences / "90" / "loops.txt").tolist()}
        return loops, [pair for pair in loops if tuple(sorted(pair)) not in truth]

    def test_a_revisit_twice_as_fast_is_found(self, kitti_sequences, encoder):
        loops, false = self.stream(kitti_sequences, encoder, [1.0, 2.0, 3.0])
        assert not false, false
        assert len({q for q, _ in loops}) >= 35  # measured (detect): 49 of the 50 queries

    def test_at_the_maps_speed_only_it_is_not(self, kitti_sequences, encoder):
        loops, _ = self.stream(kitti_sequences, encoder, [1.0])
        assert not loops
