"""cae_lcd.fleet.consistency: inter-robot edges that agree with nothing are left out of the pose graph, so a robot that sends
garbage (random rigid poses, edges made of them) moves no other robot's map; on real KITTI 00 ground-truth poses
(robots A and B as in test_graph, a hostile robot H)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from cae_lcd.fleet.consistency import PairwiseConsistency
from cae_lcd.fleet.graph import Node, PoseGraph
from cae_lcd.fleet.sim3 import Sim3

EVEN, ODD = list(range(0, 200, 2)), list(range(1, 200, 2))


def random_rigid(rng: np.random.Generator, spread: float = 500.0) -> Sim3:
    return Sim3(1.0, cv2.Rodrigues(rng.normal(0, 2.0, 3))[0], rng.uniform(-spread, spread, 3))


@pytest.fixture(scope="module")
def gt00(kitti_poses) -> list[Sim3]:
    return [Sim3.from_pose(p) for p in kitti_poses("00")]


def fleet(gt00, known_sim3, hostile: bool, conf=None) -> dict:
    """A (even frames, the global frame), B (odd frames in B's map, true overlap edges at both ends) and, when
    ``hostile``, H: 60 keyframes of random rigid poses, with random overlap edges to A and to B."""
    g = PoseGraph(conf)
    for f in EVEN:
        g.add_keyframe("A", f, gt00[f].matrix())
    in_b = {f: known_sim3.inverse().compose(gt00[f]) for f in ODD}
    b_local = {f: Sim3(1.0, T.R, T.t) for f, T in in_b.items()}  # B's rigid poses in its own map
    for f in ODD:
        g.add_keyframe("B", f, b_local[f].matrix())
    for fa, fb in [(0, 1), (2, 3), (4, 5), (196, 197), (198, 199)]:
        g.add_edge("overlap", Node("A", fa), Node("B", fb), gt00[fa].inverse().compose(known_sim3).compose(b_local[fb]))
    if hostile:
        rng = np.random.default_rng(19)
        for k in range(60):
            g.add_keyframe("H", k, random_rigid(rng).matrix())
        for k in range(0, 60, 3):
            g.add_edge("overlap", Node("A", EVEN[rng.integers(100)]), Node("H", k), random_rigid(rng, 20.0))
            g.add_edge("overlap", Node("B", ODD[rng.integers(100)]), Node("H", k + 1), random_rigid(rng, 20.0))
    return g.optimize().poses


class TestPairwiseConsistency:
    def test_the_agreeing_edges_are_kept_the_others_left_out(self, gt00):
        rng = np.random.default_rng(0)
        T = Sim3(2.0, cv2.Rodrigues(np.array([0.1, 0.6, -0.2]))[0], np.array([5.0, 1.0, -3.0]))
        transforms = [T] * 4 + [random_rigid(rng) for _ in range(3)]
        centres = [gt00[f].t for f in range(0, 70, 10)]
        assert PairwiseConsistency().select(transforms, centres) == [0, 1, 2, 3]
        assert PairwiseConsistency({"min_support": 5}).select(transforms, centres) == []
        assert PairwiseConsistency({"enabled": False}).select(transforms, centres) == list(range(7))

    def test_odometry_between_edges_widens_the_tolerance(self, gt00):
        T = Sim3.identity()
        turned = Sim3(1.0, cv2.Rodrigues(np.array([0.0, 0.2, 0.0]))[0], np.zeros(3))  # 11.5 deg apart
        test = PairwiseConsistency(None, {"rotation": 0.01, "translation": 0.05, "scale": 0.001})
        assert not test.consistent(T, gt00[0].t, turned, gt00[0].t, steps=1)
        assert test.consistent(T, gt00[0].t, turned, gt00[0].t, steps=400)


class TestHostileRobot:
    def test_a_garbage_robot_moves_no_other_map(self, gt00, known_sim3):
        clean, attacked = fleet(gt00, known_sim3, False), fleet(gt00, known_sim3, True)
        moved = max(np.linalg.norm(clean[n].t - attacked[n].t) for n in clean)
        assert moved < 0.1  # metres; H may merge by one of its edges, its own map then wrong
        unchecked = fleet(gt00, known_sim3, True, {"consistency": {"enabled": False}})
        assert max(np.linalg.norm(clean[n].t - unchecked[n].t) for n in clean) > 0.3  # what the test prevents
