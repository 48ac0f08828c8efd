"""cae_lcd.fleet.graph: the global pose graph on real KITTI ground-truth poses. Robot A has KITTI 00's even frames, robot B the
odd frames in another frame (the known similarity of conftest), overlap edges from the ground truth; a drifting
odometry is ground truth with a small yaw bias and noise on every step."""

from __future__ import annotations

import cv2
import gtsam
import numpy as np
import pytest

from cae_lcd.core.errors import ConfigError
from cae_lcd.fleet.graph import Node, PoseGraph, from_gtsam, mean_sim3, to_gtsam
from cae_lcd.fleet.sim3 import Sim3

EVEN, ODD = list(range(0, 200, 2)), list(range(1, 200, 2))


def rigid(T: Sim3) -> Sim3:
    return Sim3(1.0, T.R, T.t)


def drifting(poses: list[Sim3], rng: np.random.Generator, yaw_bias: float, noise: float = 0.0) -> list[Sim3]:
    """A chain of rigid poses whose steps are the ground-truth steps, each turned by ``yaw_bias`` radians (about the
    camera's y axis, down in KITTI) plus Gaussian rotation noise, translations with Gaussian noise (same sigma)."""
    out = [poses[0]]
    for a, b in zip(poses[:-1], poses[1:]):
        step = a.inverse().compose(b)
        turn = cv2.Rodrigues(rng.normal(0, noise, 3) + [0.0, yaw_bias, 0.0])[0]
        out.append(out[-1].compose(Sim3(1.0, step.R @ turn, step.t + rng.normal(0, noise, 3))))
    return out


@pytest.fixture(scope="module")
def gt00(kitti_poses) -> list[Sim3]:
    return [Sim3.from_pose(p) for p in kitti_poses("00")]


@pytest.fixture(scope="module")
def two_robots(gt00, known_sim3):
    """``build(overlaps, yaw_bias, conf, wrong)`` -> (graph, result): A's local poses are the ground truth, B's are
    its frames in B's map (``known_sim3`` maps B's map to A's), drifting by ``yaw_bias``; overlap edges are the
    ground-truth relative similarities of the ``(even, odd)`` frame pairs, ``wrong`` ones point 40 frames off."""
    b_local = {f: rigid(known_sim3.inverse().compose(gt00[f])) for f in ODD}

    def build(overlaps, yaw_bias=0.0, conf=None, wrong=()):
        g = PoseGraph(conf)
        for f in EVEN:
            g.add_keyframe("A", f, gt00[f].matrix())
        chain = drifting([b_local[f] for f in ODD], np.random.default_rng(0), yaw_bias, 0.001)
        for f, pose in zip(ODD, chain):
            g.add_keyframe("B", f, pose.matrix()[:3])
        measured = [(fa, fb, fb) for fa, fb in overlaps] + [(fa, fb, fb + 40) for fa, fb in wrong]
        for fa, fb, seen in measured:
            rel = gt00[fa].inverse().compose(known_sim3).compose(b_local[seen])
            g.add_edge("overlap", Node("A", fa), Node("B", fb), rel)
        return g, g.optimize()

    return build


def b_on_a(result, gt00) -> np.ndarray:
    """``(100,)`` distance of each B keyframe from where A's neighbouring keyframe and the true step put it."""
    return np.array([np.linalg.norm(result.poses[Node("B", f)].t
                                    - result.poses[Node("A", f - 1)].compose(gt00[f - 1].inverse()).compose(
                                        gt00[f]).t) for f in ODD])


START = [(0, 1), (2, 3), (4, 5)]
END = [(196, 197), (198, 199)]


class TestConversions:
    def test_gtsam_similarity3_maps_points_as_sim3(self, known_sim3, kitti_landmarks):
        g = to_gtsam(known_sim3)
        p = kitti_landmarks[7]
        np.testing.assert_allclose(g.transformFrom(p), known_sim3.apply(p), atol=1e-9)
        assert from_gtsam(g).errors(known_sim3) == pytest.approx((0, 0, 0), abs=1e-6)

    def test_gtsam_compose_is_sim3_compose(self, known_sim3, gt00):
        a, b = to_gtsam(known_sim3), to_gtsam(gt00[50])
        assert from_gtsam(a.compose(b)).errors(known_sim3.compose(gt00[50])) == pytest.approx((0, 0, 0), abs=1e-6)


class TestPoseGraph:
    def test_exact_edges_give_the_exact_merge(self, two_robots, gt00, known_sim3):
        g, res = two_robots(START)
        angle, scale, trans = res.transforms["B"].errors(known_sim3)
        assert angle < 0.2 and scale < 1e-3 and trans < 0.2
        assert np.all(np.array(res.transforms["A"].errors(Sim3.identity())) < [0.05, 1e-3, 0.01])  # B's noise moves A
        np.testing.assert_allclose(res.pose_matrix(Node("A", 0)), gt00[0].matrix(), atol=1e-5)  # A's frame is global
        assert b_on_a(res, gt00).max() < 3.0 and res.poses[Node("B", 99)].s == pytest.approx(2.5, rel=1e-3)

    def test_overlaps_at_the_end_remove_the_drift(self, two_robots, gt00):
        _, drifted = two_robots(START, yaw_bias=0.002)
        _, closed = two_robots(START + END, yaw_bias=0.002)
        before, after = b_on_a(drifted, gt00), b_on_a(closed, gt00)
        assert before[-1] > 8.0  # 0.002 rad a keyframe: metres off at the end
        assert after.max() < 0.5 and after[-1] < 0.1
        assert closed.error_after < 0.05 * closed.error_before

    @pytest.mark.parametrize("kernel, limit", [("huber", 2.0), ("cauchy", 0.5)])
    def test_robust_kernel_contains_a_wrong_overlap(self, two_robots, gt00, kernel, limit):
        edges = START + [(100, 101)] + END
        off = {"enabled": False}  # the kernels alone, without the consistency test
        _, plain = two_robots(edges, 0.002, {"robust": "none", "consistency": off}, wrong=[(50, 51)])
        _, robust = two_robots(edges, 0.002, {"robust": kernel, "consistency": off}, wrong=[(50, 51)])
        assert b_on_a(plain, gt00).max() > 10.0 and b_on_a(robust, gt00).max() < limit

    def test_the_consistency_test_leaves_a_wrong_overlap_out(self, two_robots, gt00):
        _, res = two_robots(START + [(100, 101)] + END, 0.002, {"robust": "none"}, wrong=[(50, 51)])
        assert b_on_a(res, gt00).max() < 0.5

    def test_a_loop_within_one_robot_reduces_drift(self, kitti_poses, kitti_sequences):
        """KITTI '90' passes twice over the same road; loop edges from its ground-truth loops.txt, true relatives."""
        gt = [Sim3.from_pose(p) for p in kitti_poses("90")]
        loops = np.loadtxt(kitti_sequences / "90" / "loops.txt", dtype=int)
        chain = drifting(gt, np.random.default_rng(1), 0.001, 0.001)
        errors = []
        for pairs in ([], [loops[loops[:, 0] == q][0] for q in (130, 160, 199)]):
            g = PoseGraph()
            for i, pose in enumerate(chain):
                g.add_keyframe("R", i, pose.matrix())
            for i, j in pairs:
                g.add_edge("loop", Node("R", int(j)), Node("R", int(i)), gt[j].inverse().compose(gt[i]))
            res = g.optimize()
            errors.append(max(np.linalg.norm(res.poses[Node("R", i)].t - gt[i].t) for i in range(100, 200)))
        assert errors[0] > 5.0 and errors[1] < 0.3 * errors[0]

    def test_unconnected_robot_is_left_out(self, gt00):
        g = PoseGraph()
        for f in (0, 2, 4):
            g.add_keyframe("A", f, gt00[f].matrix())
            g.add_keyframe("C", f, gt00[f + 1].matrix())
        res = g.optimize()
        assert set(res.transforms) == {"A"} and {n.robot for n in res.poses} == {"A"}
        g.add_edge("overlap", Node("A", 2), Node("C", 4), gt00[2].inverse().compose(gt00[5]))
        res = g.optimize()
        assert res.transforms["C"].errors(Sim3.identity())[2] < 1e-6

    def test_a_given_transform_is_the_starting_point(self, gt00, known_sim3):
        g = PoseGraph()
        g.add_keyframe("A", 0, gt00[0].matrix())
        g.add_keyframe("B", 0, rigid(known_sim3.inverse().compose(gt00[1])).matrix())
        g.add_edge("overlap", Node("A", 0), Node("B", 0), gt00[0].inverse().compose(gt00[1]))
        g.set_transform("B", known_sim3)
        assert g.initial_transforms()["B"] is known_sim3

    def test_empty_graph_gives_an_empty_result(self):
        res = PoseGraph().optimize()
        assert res.poses == {} and res.transforms == {}

    def test_bad_input_is_refused(self, gt00):
        g = PoseGraph()
        g.add_keyframe("A", 5, gt00[0].matrix())
        g.add_keyframe("B", 0, gt00[1].matrix())
        with pytest.raises(ConfigError, match="not after"):
            g.add_keyframe("A", 5, gt00[2].matrix())
        with pytest.raises(ConfigError, match="rotation"):
            g.add_keyframe("A", 6, np.c_[2 * np.eye(3) + np.diag([0, 0, 1.0]), np.zeros(3)])
        with pytest.raises(ConfigError, match="no keyframe"):
            g.add_edge("loop", Node("A", 5), Node("A", 9), Sim3.identity())
        with pytest.raises(ConfigError, match="joins"):
            g.add_edge("loop", Node("A", 5), Node("B", 0), Sim3.identity())
        with pytest.raises(ConfigError, match="kind"):
            g.add_edge("odometry", Node("A", 5), Node("B", 0), Sim3.identity())
        with pytest.raises(ConfigError, match="graph.robust"):
            PoseGraph({"robust": "tukey"})

    def test_every_conf_key_has_a_rule(self):
        assert set(PoseGraph.default_conf) == set(PoseGraph.conf_rules)


class TestMeanSim3:
    def test_mean_of_close_transforms(self, known_sim3):
        turn = cv2.Rodrigues(np.array([0.0, 0.0, 0.01]))[0]
        pair = [Sim3(2.0, known_sim3.R @ turn, [1.0, 0, 0]), Sim3(8.0, known_sim3.R @ turn.T, [3.0, 0, 0])]
        mean = mean_sim3(pair)
        assert mean.s == pytest.approx(4.0) and mean.errors(Sim3(4.0, known_sim3.R, [2.0, 0, 0]))[0] < 1e-4

    def test_empty_list_is_refused(self):
        with pytest.raises(ConfigError):
            mean_sim3([])


def test_gtsam_offers_similarity3_factors():
    """The API this module relies on (gtsam >= 4.3)."""
    for name in ("Similarity3", "BetweenFactorSimilarity3", "PriorFactorSimilarity3"):
        assert hasattr(gtsam, name)
    assert hasattr(gtsam.Values(), "atSimilarity3")
