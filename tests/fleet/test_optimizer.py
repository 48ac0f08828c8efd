"""cae_lcd.fleet.optimizer: the graph of KITTI 00's ground-truth poses solved in a worker thread."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.fleet.graph import Node, PoseGraph
from cae_lcd.fleet.optimizer import BackgroundOptimizer


@pytest.fixture
def graph(kitti_poses):
    g = PoseGraph()
    for i, p in enumerate(kitti_poses("00")[:20]):
        g.add_keyframe("A", i, p)
    return g


def owner(graph):
    """A snapshot function over ``graph`` under a lock (as the service does), counting calls."""
    lock, calls = threading.Lock(), []

    def snapshot():
        with lock:
            calls.append(1)
            return graph.copy()

    return snapshot, lock, calls


class TestBackgroundOptimizer:
    def test_wait_returns_a_solution_with_every_change(self, graph, kitti_poses):
        snapshot, lock, _ = owner(graph)
        opt = BackgroundOptimizer(snapshot)
        try:
            assert len(opt.wait().poses) == 20
            with lock:
                graph.add_keyframe("A", 20, kitti_poses("00")[20])
            opt.changed()
            result = opt.wait()
            assert Node("A", 20) in result.poses
            np.testing.assert_allclose(result.pose_matrix(Node("A", 20))[:3], kitti_poses("00")[20], atol=1e-6)
        finally:
            opt.close()

    def test_latest_does_not_wait_and_publish_sees_each_result(self, graph):
        published = []
        opt = BackgroundOptimizer(owner(graph)[0], published.append)
        try:
            opt.latest()  # never blocks, empty or solved
            result = opt.wait()
            assert published and published[-1] is result and opt.latest() is result
        finally:
            opt.close()

    def test_a_failed_solve_keeps_the_worker_alive(self, graph):
        snapshot, _, calls = owner(graph)
        fail = [True]

        def flaky():
            if fail.pop() if fail else False:
                raise RuntimeError("solver failed")
            return snapshot()

        opt = BackgroundOptimizer(flaky, conf={"min_interval_s": 0.0})
        try:
            assert opt.wait().poses == {}  # the failed first solve: the (empty) last result is served
            opt.changed()
            assert len(opt.wait().poses) == 20 and calls
        finally:
            opt.close()

    def test_synchronous_mode_solves_in_the_reader(self, graph):
        opt = BackgroundOptimizer(owner(graph)[0], conf={"background": False})
        assert opt._thread is None and len(opt.wait().poses) == 20
        opt.close()

    def test_changes_while_solving_are_batched(self, graph):
        snapshot, _, calls = owner(graph)
        opt = BackgroundOptimizer(snapshot, conf={"min_interval_s": 0.3})
        try:
            opt.wait()
            for _ in range(20):
                opt.changed()
            opt.wait()
            assert len(calls) <= 3
        finally:
            opt.close()

    def test_bad_conf_is_refused(self, graph):
        with pytest.raises(ConfigError, match="min_interval_s"):
            BackgroundOptimizer(owner(graph)[0], conf={"min_interval_s": -1})
