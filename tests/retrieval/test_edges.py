"""Loop edges for a back end (``retrieval.edges`` and the run folder's ``loop_edges.*``): the relative pose of real
sample revisits agrees with the ground-truth poses, and the g2o file loads in gtsam."""

from __future__ import annotations

import json

import numpy as np
import pytest

from retrieval.edges import ROTATION_SIGMA_1, LoopEdge, edge_errors, loop_edges, rotation_to_quaternion
from retrieval.run_folder import EDGE_COLUMNS, RunFolder

PAIRS = [(55, 5), (60, 10), (75, 25), (99, 49)]  #: real revisits of the bundled sample (loops.txt)


def test_quaternion_matches_gtsam():
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(0)
    for _ in range(20):
        R = gtsam.Rot3.Expmap(rng.normal(size=3) * 1.5).matrix()
        q = gtsam.Rot3(R).toQuaternion()
        expected = np.array([q.x(), q.y(), q.z(), q.w()]) * np.sign(q.w())
        assert np.allclose(rotation_to_quaternion(R), expected, atol=1e-9)


def test_real_revisits_give_the_ground_truth_rotation(sift_features, sample_K, sample_seq):
    edges = loop_edges(sift_features, PAIRS, sample_K, {})
    assert [(e.query, e.match) for e in edges] == PAIRS
    errors = edge_errors(edges, sample_seq.poses)
    assert (errors[:, 0] < 2.0).all() and (errors[:, 1] < 20.0).all()
    for e in edges:
        assert abs(np.linalg.norm(e.t) - 1.0) < 1e-6 and e.inliers > 20
        info = e.information()
        assert info.shape == (6, 6) and np.isclose(info[3, 3], e.inliers / ROTATION_SIGMA_1**2)


def test_without_intrinsics_there_is_no_pose(sift_features):
    assert loop_edges(sift_features, PAIRS, None, {}) == []


def test_empty_edges_still_write_the_files(tmp_path):
    run = RunFolder(tmp_path)
    run.write_edges([], None)
    assert run.edges_g2o.read_text() == "" and run.read_edges().shape == (0, len(EDGE_COLUMNS))
    assert json.loads(run.edges_json.read_text())["edges"] == []


def test_a_turned_edge_round_trips_through_gtsam(tmp_path):
    gtsam = pytest.importorskip("gtsam")
    R = gtsam.Rot3.Ypr(0.4, -0.2, 0.1).matrix()
    edge = LoopEdge(7, 3, 40, R, np.array([0.6, 0.0, 0.8]))
    RunFolder(tmp_path).write_edges([edge], None)
    graph, _ = gtsam.readG2o(str(tmp_path / "loop_edges.g2o"), True)
    factor = graph.at(0)
    assert list(factor.keys()) == [3, 7]
    assert np.allclose(factor.measured().rotation().matrix(), R, atol=1e-8)
    assert np.allclose(factor.measured().translation(), edge.t, atol=1e-8)


def test_the_detect_run_writes_edges_a_back_end_loads(cli_sample_run, sample_seq):
    gtsam = pytest.importorskip("gtsam")
    code, out = cli_sample_run
    assert code == 0
    run = RunFolder(out)
    loops, edges = run.read_loops(), run.read_edges()
    assert len(edges) == len(loops) > 0
    assert np.array_equal(edges[:, :2], loops[:, :2])
    # the same verification on the stored features (keypoints kept to 1/8 pixel): the same inliers, within a few
    # (RANSAC on points moved by the rounding; at 384 px, measured: median 1, at most 7 % of the pair's count)
    diff = np.abs(edges[:, 2] - loops[:, 4])
    assert np.median(diff) <= 2 and (diff <= 0.1 * loops[:, 4]).all()
    graph, initial = gtsam.readG2o(str(run.edges_g2o), True)
    assert graph.size() == len(loops) and initial.size() > 0
    from_g2o = [LoopEdge(int(f.keys()[1]), int(f.keys()[0]), 0, f.measured().rotation().matrix(),
                         f.measured().translation()) for f in (graph.at(i) for i in range(graph.size()))]
    for edge_list in (from_g2o, run.read_edge_list()):
        errors = edge_errors(edge_list, sample_seq.poses)[:, 0]
        assert np.median(errors) < 1.0 and errors.max() < 5.0
    assert "up to scale" in json.loads(run.edges_json.read_text())["note"]
    assert json.loads(run.summary.read_text())["loop_edges"] == len(loops)
