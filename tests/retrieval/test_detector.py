"""The streaming API on the bundled sample: detection quality against ground truth, resume, ids, gate, results."""

import csv
import json

import numpy as np
import pytest

from cae.conf import ConfigError
from evaluation.metrics import precision_recall
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
        n_loaded = len(det.index)
        results += run(det, range(RESUME_AT, len(seq)))
    return {"results": results, "next_id": next_id, "n_loaded": n_loaded, "db": db_path}


def loops_of(results):
    return np.array([(r.frame_id, r.loop.frame_id) for r in results if r.loop is not None], np.int64).reshape(-1, 2)


class TestLoopDetector:
    def test_precision_recall_on_sample(self, stream_run, sample_seq):
        loops = loops_of(stream_run["results"])
        pr = precision_recall(loops, sample_seq.loops)
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
        assert set(map(tuple, loops_of(stream_run["results"]).tolist())) == cli_loops
        with KeyframeDatabase(stream_run["db"], mode="r") as db:
            assert len(db) == 100 and db.last_frame_id() == 99
            recs = list(db)
        assert [r.frame_id for r in recs] == list(range(100))
        assert {(r.frame_id, r.loop) for r in recs if r.loop >= 0} == cli_loops

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
            scores = [c.score for c in r.candidates]
            assert scores == sorted(scores, reverse=True)
            if r.loop is not None:
                assert r.loop in r.candidates
                assert r.loop.matches >= policy["min_matches"] and r.loop.inliers >= policy["min_inliers"]
                assert r.loop.inliers == max(c.inliers for c in r.candidates)
                assert r.R.shape == (3, 3) and r.t.shape == (3,)
                np.testing.assert_allclose(r.R @ r.R.T, np.eye(3), atol=1e-6)
                assert np.linalg.norm(r.t) == pytest.approx(1.0, abs=1e-6)
        assert all(not r.candidates and r.loop is None for r in results[:50])

    def test_to_dict_json(self, stream_run):
        loop_frame = next(r for r in stream_run["results"] if r.loop is not None)
        for r in (stream_run["results"][0], loop_frame):
            d = json.loads(json.dumps(r.to_dict()))
            assert d["frame_id"] == r.frame_id and d["gated"] is False
            assert len(d["candidates"]) == len(r.candidates)
        d = json.loads(json.dumps(loop_frame.to_dict()))
        assert d["loop"] == {"frame_id": loop_frame.loop.frame_id, "score": loop_frame.loop.score,
                             "matches": loop_frame.loop.matches, "inliers": loop_frame.loop.inliers}
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

    def test_gated_frame(self, encoder, tmp_path):
        grey = np.full((188, 620), 128, np.uint8)
        with LoopDetector(encoder=encoder, database=tmp_path / "kf.h5") as det:
            res = det.process(grey, 0)
            assert res.gated and res.edge_ratio == 0.0
            assert res.candidates == [] and res.loop is None and res.R is None
            assert "encode" not in res.ms
            assert json.loads(json.dumps(res.to_dict()))["gated"] is True
            assert len(det.index) == 0
        with KeyframeDatabase(tmp_path / "kf.h5", mode="r") as db:
            assert len(db) == 0 and db.gated().tolist() == [0] and db.last_frame_id() == 0
        with LoopDetector(encoder=encoder, database=tmp_path / "kf.h5") as det:
            assert det.next_frame_id == 1

    def test_short_sequence_sequential_equals_parallel(self, encoder, sample_image, sample_K):
        """Frames 0, 1, 2 then their revisits 50, 51, 52 (as ids 3, 4, 5), with a short exclusion window."""
        frames = [0, 1, 2, 50, 51, 52]
        conf = {"search": {"exclude_recent": 3}}
        out = {}
        for parallel in (True, False):
            with LoopDetector({**conf, "runtime": {"parallel": parallel}}, K=sample_K, encoder=encoder) as det:
                out[parallel] = [det.process(sample_image(i)) for i in frames]
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
            assert len(det.features) == 0 and len(det.index) == RESUME_AT
            results += [det.process(sample_image(i), i, float(seq.timestamps[i])) for i in range(RESUME_AT, len(seq))]
            assert len(det.features) <= 8
        assert np.array_equal(loops_of(results), loops_of(stream_run["results"]))

    def test_database_mode_needs_a_database(self, encoder):
        with pytest.raises(ConfigError, match="needs a keyframe database"):
            LoopDetector({"runtime": {"features": "database"}}, encoder=encoder)
        with pytest.raises(ConfigError, match="runtime.features"):
            LoopDetector({"runtime": {"features": "disk"}}, encoder=encoder)


class TestCandidate:
    def test_as_row(self):
        assert Candidate(3, 0.5, 10, 7).as_row() == (3, 0.5, 10, 7)
