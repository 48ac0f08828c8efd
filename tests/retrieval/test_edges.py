"""Loop edges for a back end (``retrieval.edges`` and the run folder's ``loop_edges.*``): the relative pose of real
sample revisits agrees with the ground-truth poses, its information comes from the inliers' residuals and says
the translation's length is unknown, the g2o file loads in gtsam, and a KITTI 90 pose graph with drifted odometry
is helped by the edges as written at least as much as by their rotations, with a consistent chi-square."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from retrieval.edges import LoopEdge, edge_errors, g2o_order, loop_edges, rotation_to_quaternion
from retrieval.run_folder import EDGE_COLUMNS, FrameKeys, RunFolder, key_columns
from verify.geometry import UNOBSERVED_INFORMATION, pose_information

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
    sigmas = np.degrees([e.sigmas()[0] for e in edges])
    assert (errors[:, 0] < 4 * sigmas).all()  # the information is not over-confident on real revisits
    for e in edges:
        assert abs(np.linalg.norm(e.t) - 1.0) < 1e-6 and e.inliers > 20 and not e.metric
        info = e.information()
        assert info.shape == (6, 6) and np.allclose(info, info.T)
        w, v = np.linalg.eigh(info)
        # rank 5: nothing is known along the translation (its length), in g2o's order translation first
        assert w[0] == pytest.approx(UNOBSERVED_INFORMATION, rel=1e-2) and w[1] > 10
        assert abs(v[:3, 0] @ (e.R.T @ e.t)) > 0.999


def test_a_pair_the_run_verified_is_not_verified_again(sift_features, sample_K):
    """``loop_edges``' ``verified``: a pair whose check the run kept takes that geometry (its features are not even
    asked for) and gives the edge its own verification would; a pair it has none for is verified from the
    features."""
    from verify.verifier import create_verifier

    kept = {pair: create_verifier().verify(sift_features(pair[0]), [sift_features(pair[1])], sample_K)[0].geometry
            for pair in PAIRS[:2]}
    asked = []
    edges = loop_edges(lambda i: asked.append(i) or sift_features(i), PAIRS, sample_K, {},
                       verified=lambda q, m: kept.get((q, m)))
    assert sorted(set(asked)) == sorted({f for pair in PAIRS[2:] for f in pair})  # the kept pairs: no features
    again = loop_edges(sift_features, PAIRS, sample_K, {})
    assert [(e.query, e.match) for e in edges] == PAIRS
    for e, a, pair in zip(edges, again, PAIRS):
        if pair in kept:
            assert e.inliers == kept[pair].inliers
            np.testing.assert_allclose(e.R, kept[pair].refined[0], atol=1e-12)
        rotation = np.degrees(np.linalg.norm(cv2.Rodrigues(e.R.T @ a.R)[0]))
        assert rotation < 0.5 and abs(e.inliers - a.inliers) <= max(5, 0.1 * a.inliers)


def test_poses_refined_ahead_are_the_poses_made_after(sift_features, sample_K):
    """``PosesAhead`` (``detect`` refines its loops' poses beside the stream): after ``close`` each kept check holds
    its refined pose, the one a fresh check of the pair refines; a pair without a kept check is left alone."""
    from retrieval.edges import PosesAhead
    from verify.verifier import create_verifier

    kept = {pair: create_verifier().verify(sift_features(pair[0]), [sift_features(pair[1])], sample_K)[0].geometry
            for pair in PAIRS[:3]}
    with PosesAhead(lambda q, m: kept.get((q, m))) as poses:
        poses.add(PAIRS)
    for pair, geo in kept.items():
        assert "_kept_refined" in vars(geo)  # made ahead, not on the read below
        fresh = create_verifier().verify(sift_features(pair[0]), [sift_features(pair[1])], sample_K)[0].geometry
        np.testing.assert_array_equal(geo.refined[0], fresh.refined[0])


def test_poses_refine_side_by_side(sift_features, sample_K, monkeypatch):
    """A check's refined pose is kept without a lock shared by every check (``functools.cached_property``'s before
    Python 3.12 made two threads refine one pose at a time): two threads refining two pairs each compute at once."""
    import threading

    from verify import geometry
    from verify.verifier import create_verifier

    geos = [create_verifier().verify(sift_features(q), [sift_features(m)], sample_K)[0].geometry for q, m in PAIRS[:2]]
    inside, both, met = [0], threading.Event(), []
    refine = geometry.refined_pose

    def counted(*args, **kwargs):
        inside[0] += 1
        if inside[0] == 2:
            both.set()
        met.append(both.wait(2))  # the first waits here until the second is inside too (False: it never came)
        return refine(*args, **kwargs)

    monkeypatch.setattr(geometry, "refined_pose", counted)
    threads = [threading.Thread(target=getattr, args=(g, "refined")) for g in geos]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert met == [True, True]


def test_edges_side_by_side_are_the_edges_one_after_another(sample_seq, sample_K):
    """``loop_edges`` on two threads with ``edge_features`` (frames read again and extracted side by side) gives the
    edges one thread gives, in the same order; a frame that cannot be read takes the fallback's features."""
    from retrieval.edges import edge_features

    conf = {"name": "sift", "resize_max": 512}
    fallback = []

    def read(i):
        return "unreadable" if i == 99 else sample_seq.read_frame(i)[0]

    def features():
        from verify.features import create_extractor

        extractor = create_extractor(conf)
        return edge_features(read, conf, lambda i: fallback.append(i) or extractor.extract(sample_seq.read_frame(i)[0]))

    one = loop_edges(features(), PAIRS, sample_K, {})
    two = loop_edges(features(), PAIRS, sample_K, {}, workers=2)
    assert [(e.query, e.match, e.inliers) for e in two] == [(e.query, e.match, e.inliers) for e in one]
    assert len(one) == len(PAIRS) and fallback == [99, 99]
    for a, b in zip(one, two):
        np.testing.assert_allclose(b.R, a.R, atol=1e-12)
        np.testing.assert_allclose(b.information(), a.information(), rtol=1e-9)


def test_only_the_unsure_edges_are_made_again_from_finer_features(sift_features, sample_K):
    """With ``precise``, the edges the run's own features give surely are kept as they are, and only the unsure one
    (frame 99 left with a few of its keypoints: a rotation far less certain than the others') is made again from the
    finer features, whose frames alone are asked for."""
    from verify.features import Features

    def thinned(i):
        f = sift_features(i)
        return Features(f.keypoints[:40], f.descriptors[:40], f.scales[:40], f.metric) if i == 99 else f

    asked = []
    own = loop_edges(thinned, PAIRS, sample_K, {}, workers=2)
    both = loop_edges(thinned, PAIRS, sample_K, {}, workers=2, precise=lambda i: asked.append(i) or sift_features(i))
    sure = loop_edges(sift_features, PAIRS, sample_K, {})
    assert sorted(asked) == [49, 99]
    assert [e.inliers for e in both] == [e.inliers for e in own[:3]] + [sure[3].inliers]
    assert both[3].sigmas()[0] == sure[3].sigmas()[0] < own[3].sigmas()[0] / 2


def test_the_information_comes_from_the_residuals(sift_features, sample_K):
    from verify.verifier import create_verifier

    geo = create_verifier().verify(sift_features(55), [sift_features(5)], sample_K)[0].geometry
    _, a, b, K = geo.essential
    a, b = a.reshape(-1, 2), b.reshape(-1, 2)
    info, sigma = pose_information(a, b, K, geo.R, geo.t)
    noisy, sigma_noisy = pose_information(a + np.random.default_rng(0).normal(0, 2.0, a.shape), b, K, geo.R, geo.t)
    assert 0.1 < sigma < 2.0 and sigma_noisy > 2 * sigma  # the pixel noise is measured, not assumed
    assert np.trace(np.linalg.pinv(noisy)[:3, :3]) > 3 * np.trace(np.linalg.pinv(info)[:3, :3])
    few, _ = pose_information(a[:30], b[:30], K, geo.R, geo.t)
    assert np.trace(np.linalg.pinv(few)[:3, :3]) > 2 * np.trace(np.linalg.pinv(info)[:3, :3])  # fewer inliers
    assert pose_information(a[:5], b[:5], K, geo.R, geo.t)[0].sum() == 0  # too few points: no information


def test_a_metric_edge_knows_its_length(sift_features, sample_K):
    edge = loop_edges(sift_features, PAIRS[:1], sample_K, {})[0]
    metric = edge.scaled(0.5, 0.05)
    assert metric.metric and np.linalg.norm(metric.t) == pytest.approx(0.5)
    assert np.allclose(metric.t / 0.5, edge.t)
    info = g2o_order(metric.information())  # gtsam's order
    u = np.r_[np.zeros(3), edge.R.T @ edge.t]
    assert u @ info @ u == pytest.approx(1 / 0.05**2, rel=1e-6)
    assert metric.sigmas()[0] == pytest.approx(edge.sigmas()[0], rel=1e-6)  # the rotation is unchanged
    assert metric.sigmas()[1] == pytest.approx(edge.sigmas()[1], rel=1e-3)  # so is the direction's angle


def test_without_intrinsics_there_is_no_pose(sift_features):
    assert loop_edges(sift_features, PAIRS, None, {}) == []


def test_empty_edges_still_write_the_files(tmp_path):
    run = RunFolder(tmp_path)
    run.write_edges([], None)
    assert run.edges_g2o.read_text() == "" and run.read_edges().shape == (0, len(EDGE_COLUMNS))
    assert json.loads(run.edges_json.read_text())["edges"] == []
    assert "no timestamps" in run.edges_tum.read_text()


def test_edges_carry_the_frames_stamps_and_source_ids(tmp_path):
    R = np.eye(3)
    edge = LoopEdge(7, 3, 40, R, np.array([0.6, 0.0, 0.8]))
    keys = FrameKeys(np.arange(10) * 0.1 + 1700000000.0, [f"rgb/{i}.png" for i in range(10)])
    run = RunFolder(tmp_path)
    run.write_edges([edge], None, keys)
    import csv

    row = next(csv.DictReader(open(run.edges_csv)))
    assert (row["query_time"], row["match_time"]) == ("1700000000.700000048", "1700000000.299999952")
    assert (row["query_source"], row["match_source"]) == ("rgb/7.png", "rgb/3.png")
    item = json.loads(run.edges_json.read_text())["edges"][0]
    assert {k: item[k] for k in key_columns("query", "match")} == {k: row[k] for k in key_columns("query", "match")}
    tum = np.loadtxt(run.edges_tum)
    assert tum.shape == (9,) and np.allclose(tum[:2], [1700000000.7, 1700000000.3]) and np.allclose(tum[2:5], edge.t)


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
    # a calibrated run detects on 384 px features (calibration.features_px): the edges are made on them (inliers
    # within a few of what the detection counted; made at 512 px they have 1.2x more), only the unsure ones again at
    # 512 px (test_only_the_unsure_edges_are_made_again_from_finer_features; none on the sample)
    assert json.loads(run.summary.read_text())["calibration"] is not None
    assert np.median(np.abs(edges[:, 2] - loops[:, 4])) <= 5
    graph, initial = gtsam.readG2o(str(run.edges_g2o), True)
    assert graph.size() == len(loops) and initial.size() > 0
    from_g2o = [LoopEdge(int(f.keys()[1]), int(f.keys()[0]), 0, f.measured().rotation().matrix(),
                         f.measured().translation()) for f in (graph.at(i) for i in range(graph.size()))]
    for edge_list in (from_g2o, run.read_edge_list()):
        errors = edge_errors(edge_list, sample_seq.poses)[:, 0]
        assert np.median(errors) < 1.0 and errors.max() < 5.0
    assert "length is unobserved" in json.loads(run.edges_json.read_text())["note"]
    assert json.loads(run.summary.read_text())["loop_edges"] == len(loops)


def test_kitti_90_pose_graph_is_helped_by_the_edges_as_written(kitti_sequences, tmp_path):
    """Every other true loop of KITTI 90 (50 edges, the detected loops are these) in the drifted-odometry pose graph
    of ``bench.loop_edges`` (the bench runs the detector's own loops)."""
    pytest.importorskip("gtsam")
    from bench.loop_edges import pose_graph
    from cae_lcd.evaluation.ground_truth import read_loop_pairs
    from retrieval.detector import resolve_conf
    from retrieval.sequences import open_sequence
    from verify.features import create_extractor

    seq = open_sequence(kitti_sequences / "90")
    pairs = read_loop_pairs(seq.ground_truth)
    loops = [(q, int(np.median(pairs[pairs[:, 0] == q, 1]))) for q in np.unique(pairs[:, 0])[::2]]
    extractor = create_extractor(resolve_conf({})["features"])
    feats = {}

    def features(i):
        if i not in feats:
            feats[i] = extractor.extract(seq.read_frame(i)[0])
        return feats[i]

    edges = loop_edges(features, loops, seq.K, {})
    assert len(edges) == len(loops)
    run = RunFolder(tmp_path)
    run.write_edges(edges, seq.poses)
    graph = pose_graph(seq.poses, edges, run.edges_g2o)
    written, rotation = graph["edges as written"], graph["rotation only"]
    assert graph["no loops"]["end_error_m"] > 5 * written["end_error_m"]
    assert written["end_error_m"] <= rotation["end_error_m"]
    assert written["dof"] == 5 * len(edges) and 0.5 < written["chi2"] / written["dof"] < 1.5


def test_fisheye_frames_give_the_pinhole_loops_and_rotations(kitti_sequences, tmp_path):
    """KITTI 90 loop pairs (every third query, 34) seen through an equidistant lens (``bench.fisheye``), read with the
    camera's YAML: the pairs verify as they do in the pinhole frames and the edges' rotations are within 0.5 degree
    of the pinhole run's (measured: max 0.14; with RANSAC's unrefined five-point pose 1.40, query 142: its sample
    fell in the forward motion's second minimum, ``verify.geometry.refined_pose``). The full sequence through
    ``cae-lcd detect``: ``python -m bench.fisheye``."""
    from bench.fisheye import rotation_gaps, write_fisheye_sequence
    from cae_lcd.evaluation.ground_truth import read_loop_pairs
    from retrieval.detector import resolve_conf
    from retrieval.sequences import open_sequence
    from verify.camera import read_camera_file
    from verify.features import create_extractor

    seq = open_sequence(kitti_sequences / "90")
    pairs = read_loop_pairs(seq.ground_truth)
    loops = [(int(q), int(np.median(pairs[pairs[:, 0] == q, 1]))) for q in np.unique(pairs[:, 0])[::3]]
    frames = sorted({i for pair in loops for i in pair})
    folder, yaml_path = write_fisheye_sequence(seq, tmp_path / "fisheye", frames)
    camera = read_camera_file(yaml_path)
    assert camera.model == "equidistant" and np.allclose(camera.K, seq.K)
    extractor = create_extractor(resolve_conf({})["features"])
    pinhole = {i: extractor.extract(seq.read_frame(i)[0]) for i in frames}
    warped = {i: extractor.extract(open_sequence(folder).read_frame(n)[0]) for n, i in enumerate(frames)}

    def edges(feats, conf):
        return loop_edges(feats.__getitem__, loops, camera.K, {"geometry": conf})

    base = edges(pinhole, {})
    fisheye = edges(warped, camera.geometry_conf())
    assert [(e.query, e.match) for e in fisheye] == [(e.query, e.match) for e in base] == loops
    assert min(e.inliers for e in fisheye) >= 0.5 * min(e.inliers for e in base)
    assert rotation_gaps(fisheye, base).max() < 0.5


def test_metric_edges_take_the_length_from_the_poses(sift_features, sample_K, sample_seq):
    from retrieval.edges import LENGTH_SIGMA, metric_edges

    edges = loop_edges(sift_features, PAIRS, sample_K, {})
    poses = sample_seq.poses.copy()
    poses[PAIRS[-1][0]] = np.nan  # a frame without a pose: its edge stays up to scale
    metric = metric_edges(edges, poses)
    for e, m in zip(edges[:-1], metric[:-1]):
        length = np.linalg.norm(poses[e.query][:, 3] - poses[e.match][:, 3])
        assert m.metric and np.linalg.norm(m.t) == pytest.approx(length) and np.allclose(m.R, e.R)
        u = np.r_[np.zeros(3), e.R.T @ e.t]
        assert u @ g2o_order(m.information()) @ u == pytest.approx(1 / max(LENGTH_SIGMA[0] * length,
                                                                           LENGTH_SIGMA[1]) ** 2, rel=1e-6)
    assert not metric[-1].metric and metric_edges(edges, None) == edges


def test_body_edges_round_trip_and_keep_every_chi_square(sift_features, sample_K, sample_seq):
    """``body_edges``: the sample's metric edges through a turned, offset ``T_BS`` are the relative poses of the
    bodies (``T_WC T_BS^-1``), back through ``T_BS^-1`` they are the camera's again, and an error's chi-square is
    the same in both frames (the information went through the adjoint)."""
    from retrieval.edges import adjoint, body_edges, body_poses, metric_edges

    X = np.eye(4)
    X[:3, :3] = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]) @ _rot([0.1, 0.2, -0.3])
    X[:3, 3] = [-0.02, -0.06, 0.3]
    from scipy.linalg import expm

    def hat(xi):  # se(3), gtsam's order (rotation, translation)
        w = xi[:3]
        out = np.zeros((4, 4))
        out[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
        out[:3, 3] = xi[3:]
        return out

    xi = np.array([0.01, -0.02, 0.03, 0.1, 0.2, -0.1])
    np.testing.assert_allclose(X @ expm(hat(xi)) @ np.linalg.inv(X), expm(hat(adjoint(X) @ xi)), atol=1e-12)
    camera = metric_edges(loop_edges(sift_features, PAIRS, sample_K, {}), sample_seq.poses)
    body = body_edges(camera, X)
    bodies = body_poses(sample_seq.poses, X)
    cam_err, body_err = edge_errors(camera, sample_seq.poses), edge_errors(body, bodies)
    np.testing.assert_allclose(body_err[:, 0], cam_err[:, 0], atol=1e-6)  # the same rotation error, turned
    for e, b in zip(camera, body):
        Bm, Bq = np.vstack([bodies[e.match], [0, 0, 0, 1]]), np.vstack([bodies[e.query], [0, 0, 0, 1]])
        truth = np.linalg.inv(Bm) @ Bq
        C = np.linalg.inv(np.vstack([sample_seq.poses[e.match], [0, 0, 0, 1]])) @ np.vstack(
            [sample_seq.poses[e.query], [0, 0, 0, 1]])
        # the translation error is the camera's, seen from the body: no larger than the camera's own
        assert np.linalg.norm(b.t - truth[:3, 3]) < np.linalg.norm(e.t - C[:3, 3]) + 0.1 * np.linalg.norm(X[:3, 3])
        assert np.linalg.norm(b.t - truth[:3, 3]) < 0.1
        back = body_edges([b], np.linalg.inv(X))[0]
        np.testing.assert_allclose(back.R, e.R, atol=1e-9)
        np.testing.assert_allclose(back.t, e.t, atol=1e-9)
        np.testing.assert_allclose(back.information(), e.information(), rtol=1e-6, atol=1e-6)
        xi = np.random.default_rng(e.query).normal(size=6) * 1e-2  # an error in the camera's tangent (gtsam order)
        xi_body = adjoint(X) @ xi
        assert xi_body @ g2o_order(b.information()) @ xi_body == pytest.approx(
            xi @ g2o_order(e.information()) @ xi, rel=1e-6)


def _rot(v):
    import cv2

    return cv2.Rodrigues(np.asarray(v, np.float64).reshape(3, 1))[0]
