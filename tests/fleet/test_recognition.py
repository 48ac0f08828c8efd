"""fleet.recognition on real KITTI frames: robots A (even frames) and B (odd frames, poses in a known other map) of
00 overlap; 00 and 07 never meet."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from core.conf import ConfigError
from fleet.recognition import FleetRecognizer, remembering
from fleet.sim3 import Sim3


@pytest.fixture(scope="module")
def kitti(kitti_sequences, kitti_poses):
    """``frame(seq, i)`` -> (image, pose (4, 4), K)."""
    from retrieval.sequences import read_kitti_calib

    poses = {s: kitti_poses(s) for s in ("00", "07", "90")}
    calib = {s: read_kitti_calib(kitti_sequences / s / "calib.txt") for s in ("00", "07", "90")}

    def frame(seq: str, i: int):
        image = cv2.imread(str(kitti_sequences / seq / "image_0" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        return image, Sim3.from_pose(poses[seq][i]).matrix(), calib[seq]

    return frame


def in_other_map(pose: np.ndarray, truth: Sim3) -> np.ndarray:
    """The pose in B's map (``truth`` of the world), rigid in B's units."""
    return truth.compose(Sim3.from_pose(pose)).compose(Sim3(1 / truth.s, np.eye(3), np.zeros(3))).matrix()


def stream(rec, kitti, frames, known_sim3=None):
    """Feeds (robot, seq, frame) triples; returns every Recognition."""
    out = []
    for robot, seq, i in frames:
        image, pose, K = kitti(seq, i)
        if robot == "B" and known_sim3 is not None:
            pose = in_other_map(pose, known_sim3)
        out.append(rec.process(robot, i, float(i), pose, image, K))
    return out


@pytest.fixture(scope="module")
def overlapping(tmp_path_factory, kitti, cae_descriptor, known_sim3):
    """A recognizer after A = 00 frames 100, 102, ..., 118 and B = 101, ..., 119 (B in ``known_sim3``'s map)."""
    state = tmp_path_factory.mktemp("fleet_state")
    rec = FleetRecognizer(state, descriptor=cae_descriptor)
    found = stream(rec, kitti, [("A" if i % 2 == 0 else "B", "00", i) for i in range(100, 120)], known_sim3)
    rec.close()
    return state, found


class TestRemembering:
    def test_same_class_same_code_remembered(self, cae_descriptor, kitti):
        d = remembering(cae_descriptor)
        image = kitti("00", 0)[0]
        assert isinstance(d, type(cae_descriptor)) and d.encoder is cae_descriptor.encoder
        code = d(image)
        np.testing.assert_array_equal(code, cae_descriptor(image))
        assert d.last is code


class TestFleetRecognizer:
    def test_overlap_is_accepted_with_the_known_transform(self, overlapping, known_sim3):
        _, found = overlapping
        overlaps = [o for r in found for o in r.overlaps]
        assert len(overlaps) == 1  # recorded once for the pair
        first = next(i for i, r in enumerate(found) if r.overlaps)
        assert first >= 2 * 3 - 1  # not before 3 consecutive matches of one robot
        angle, scale, _ = overlaps[0].transform.errors(known_sim3.inverse() if overlaps[0].robot_a == "A"
                                                       else known_sim3)
        assert angle < 2.0 and scale < 0.05

    def test_every_edge_is_an_overlap_close_to_the_truth(self, overlapping, known_sim3, kitti):
        _, found = overlapping
        edges = [e for r in found for e in r.edges]
        assert len(edges) >= 5 and {e.kind for e in edges} == {"overlap"}
        unit_b = Sim3(1 / known_sim3.s, np.eye(3), np.zeros(3))  # a B camera's frame is in B's units
        node = {"A": lambda i: Sim3.from_pose(kitti("00", i)[1]),
                "B": lambda i: Sim3.from_pose(kitti("00", i)[1]).compose(unit_b)}
        for e in edges:
            truth = node[e.robot_a](e.keyframe_a).inverse().compose(node[e.robot_b](e.keyframe_b))
            angle, scale, _ = e.relative.errors(truth)
            assert angle < 3.0 and scale < 0.05

    def test_the_budget_bounds_the_candidates_verified(self, tmp_path, kitti, cae_descriptor):
        """Four robots on KITTI 00 and 07: a keyframe verifies at most ``cross.budget`` other robots' candidates."""
        rec = FleetRecognizer(tmp_path, {"cross": {"budget": 2, "k": 3}}, descriptor=cae_descriptor)
        verified = []
        frames = [(r, s, i) for i in (0, 2) for r, s in (("A", "00"), ("B", "07"), ("C", "00"), ("D", "07"))]
        stream(rec, kitti, frames[:4])
        for r in rec.robots.values():
            real = r.detector.verifier.verify
            r.detector.verifier.verify = lambda q, cands, *a, _real=real, **kw: verified.append(len(cands)) or \
                _real(q, cands, *a, **kw)
        stream(rec, kitti, [("A", "00", 4)])
        rec.close()
        assert sum(verified) == 2  # 3 other robots x 1 keyframe each would be 3 without the budget

    def test_robots_that_never_meet_have_no_overlap(self, tmp_path, kitti, cae_descriptor):
        rec = FleetRecognizer(tmp_path, descriptor=cae_descriptor)
        found = stream(rec, kitti, [(r, s, i) for i in range(0, 40, 2) for r, s in (("A", "00"), ("B", "07"))])
        rec.close()
        assert not [e for r in found for e in r.edges] and not [o for r in found for o in r.overlaps]

    def test_a_robot_revisiting_a_place_reports_a_loop(self, tmp_path, kitti, cae_descriptor):
        """KITTI 90: frames 134-145 drive again past frames 34-45 (about 0.7 m beside them)."""
        rec = FleetRecognizer(tmp_path, descriptor=cae_descriptor)
        found = stream(rec, kitti, [("A", "90", i) for i in [*range(34, 46), *range(134, 146)]])
        rec.close()
        loops = [e for r in found for e in r.edges]
        assert loops and {e.kind for e in loops} == {"loop"} and not [o for r in found for o in r.overlaps]
        for e in loops:
            assert e.robot_a == e.robot_b == "A" and e.keyframe_a < 46 and e.keyframe_b >= 134
            truth = Sim3.from_pose(kitti("90", e.keyframe_a)[1]).inverse().compose(
                Sim3.from_pose(kitti("90", e.keyframe_b)[1]))
            angle, scale, trans = e.relative.errors(truth)
            assert angle < 3.0 and scale < 0.05 and trans < 1.0  # metres, scenes 10-30 m deep

    def test_a_restarted_recognizer_continues(self, overlapping, cae_descriptor, kitti):
        state, _ = overlapping
        rec = FleetRecognizer(state, descriptor=cae_descriptor)
        try:
            assert sorted(rec.robots) == ["A", "B"]
            assert rec.robots["A"].ids == list(range(100, 120, 2))
            assert rec.has("B", 119) and not rec.has("B", 121)
            np.testing.assert_allclose(rec.robots["A"].K, kitti("00", 0)[2])
            with pytest.raises(ConfigError, match="not after"):
                stream(rec, kitti, [("A", "00", 118)])
        finally:
            rec.close()

    def test_a_resumed_overlap_stays_accepted(self, overlapping, cae_descriptor, kitti, known_sim3):
        state, found = overlapping
        rec = FleetRecognizer(state, descriptor=cae_descriptor)
        try:
            rec.resume([o for r in found for o in r.overlaps], [e for r in found for e in r.edges])
            after = stream(rec, kitti, [("A", "00", 120), ("B", "00", 121)], known_sim3)
        finally:
            rec.close()
        assert not [o for r in after for o in r.overlaps]  # recorded once, before the restart
        assert [e.kind for r in after for e in r.edges][:1] == ["overlap"]  # no new run of 3 needed

    def test_other_intrinsics_are_refused(self, overlapping, cae_descriptor, kitti):
        rec = FleetRecognizer(overlapping[0], descriptor=cae_descriptor)
        try:
            image, pose, K = kitti("00", 130)
            with pytest.raises(ConfigError, match="intrinsics differ"):
                rec.process("A", 130, 130.0, pose, image, K * 2)
            assert not rec.has("A", 130)
        finally:
            rec.close()

    @pytest.mark.parametrize("conf, key", [({"cross": {"k": 0}}, "cross.k"), ({"min_points": 1}, "min_points"),
                                           ({"detector": {"search": {"k": "x"}}}, "search.k")])
    def test_bad_conf_is_refused_before_anything_is_written(self, tmp_path, conf, key, cae_descriptor):
        with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
            FleetRecognizer(tmp_path / "s", conf, descriptor=cae_descriptor)
        assert not (tmp_path / "s").exists()
