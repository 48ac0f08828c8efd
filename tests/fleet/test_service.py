"""cae_lcd.fleet.service (issue 29): the global frame never moves under a robot's feet (a stored anchor, both stores), the
admin's actions (name the anchor, reset, retire, rotate a token) and a robot that locked itself out reset. Real KITTI
00 ground-truth poses; overlaps come as edges (no recognition: fast)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import ConflictError
from cae_lcd.fleet.service import FleetService
from cae_lcd.fleet.sim3 import Sim3
from cae_lcd.fleet.store import EdgeRecord
from cae_lcd.fleet.stores import open_store

FAST = {"token_iterations": 1000}


@pytest.fixture(params=["sqlite", "postgres"])
def location(request, tmp_path):
    """Where a store lives: a SQLite file, or a PostgreSQL database of the session's server."""
    if request.param == "sqlite":
        return str(tmp_path / "fleet.sqlite")
    return request.getfixturevalue("local_postgres").create_database(f"svc{abs(hash(str(tmp_path))) % 10**8}")


def service_on(location: str) -> FleetService:
    return FleetService(open_store("unused", location, FAST))


def stream_two_robots(service: FleetService, kitti_poses, known_sim3, n: int = 200) -> None:
    """RA streams KITTI 00's even frames in its own frame (the ground truth's), RB the odd ones in a frame
    ``known_sim3`` away; every 10th pair overlaps (an edge from the ground truth)."""
    gt = [Sim3.from_pose(p) for p in kitti_poses("00")[:n]]
    local_b = {}
    for i in range(n):
        robot = "RA" if i % 2 == 0 else "RB"
        pose = gt[i] if robot == "RA" else known_sim3.inverse().compose(gt[i])
        local_b[i] = Sim3(1.0, pose.R, pose.t)
        service.submit_keyframe(robot, i, 0.1 * i, np.c_[pose.R, pose.t])
        if robot == "RB" and i % 20 == 1:
            rel = gt[i - 1].inverse().compose(known_sim3).compose(local_b[i])
            service.add_edge(EdgeRecord("overlap", "RA", i - 1, "RB", i, rel, 40.0))


def maps(service: FleetService) -> dict[str, np.ndarray]:
    """RA's and RB's corrected poses (stacked) and transforms, after a solution with every keyframe so far."""
    out = {r: np.array([p["pose"] for p in service.poses(r, wait=True)]) for r in ("RA", "RB")}
    transforms = service.store.transforms()
    out.update({f"T_{r}": transforms[r].matrix() for r in ("RA", "RB")})
    return out


class TestAnchor:
    def test_a_robot_registered_earlier_speaking_later_moves_no_map(self, location, kitti_poses, known_sim3):
        """Z0 registered first, silent while RA and RB merge; its one keyframe (identity pose) changes neither
        RA's nor RB's corrected poses nor their transforms, nor after a restart (the audit: both became [])."""
        service = service_on(location)
        for name in ("Z0", "RA", "RB"):
            service.register(name)
        stream_two_robots(service, kitti_poses, known_sim3)
        before = maps(service)
        assert len(before["RA"]) == len(before["RB"]) == 100 and service.anchor == "RA"
        service.submit_keyframe("Z0", 0, 0.0, np.eye(4))
        after = maps(service)
        assert service.anchor == "RA" and service.poses("Z0", wait=True) == []  # not merged: no overlap yet
        for key in before:
            np.testing.assert_allclose(after[key], before[key], atol=1e-6, err_msg=key)
        service.close()
        service = service_on(location)  # a restart: the anchor is the stored one, not the first registered
        try:
            assert service.anchor == "RA"
            again = maps(service)
            for key in before:
                np.testing.assert_allclose(again[key], before[key], atol=1e-6, err_msg=key)
        finally:
            service.close()

    def test_a_lone_robot_that_spoke_first_is_not_the_fleets_frame(self, tmp_path, kitti_poses, known_sim3):
        """H (say a hostile robot) sends first and never merges: the first merged maps, RA's and RB's, are the
        fleet's; H's keyframes, before and after, move nothing."""
        service = service_on(str(tmp_path / "fleet.sqlite"))
        try:
            for name in ("H", "RA", "RB"):
                service.register(name)
            service.submit_keyframe("H", 0, 0.0, np.eye(4))
            assert service.anchor == "H"  # provisional: nobody merged yet
            stream_two_robots(service, kitti_poses, known_sim3, 60)
            assert service.anchor == "RA" and service.store.anchor() == "RA"
            before = maps(service)
            service.submit_keyframe("H", 1, 1.0, np.eye(4))
            after = maps(service)
            for key in before:
                np.testing.assert_allclose(after[key], before[key], atol=1e-6, err_msg=key)
        finally:
            service.close()

    def test_the_admin_names_another_anchor_and_every_map_is_re_expressed(self, location, kitti_poses, known_sim3,
                                                                          caplog):
        service = service_on(location)
        try:
            for name in ("RA", "RB", "Z0"):
                service.register(name)
            stream_two_robots(service, kitti_poses, known_sim3, 60)
            before = maps(service)
            with pytest.raises(ConfigError, match="no keyframes"):
                service.set_anchor("Z0")
            with caplog.at_level(logging.WARNING, "cae_lcd.fleet.service"):
                service.set_anchor("RB")
            assert any("admin: the anchor" in r.getMessage() for r in caplog.records)
            after = maps(service)
            np.testing.assert_allclose(after["T_RB"], np.eye(4), atol=1e-6)
            moved = Sim3.from_matrix(after["T_RA"])  # RA's map in RB's frame: the inverse of known_sim3
            assert max(moved.errors(known_sim3.inverse())) < 1e-3
            # the same map, another frame: poses differ by that one similarity
            np.testing.assert_allclose(after["RA"][:, :3, 3], [moved.compose(Sim3.from_matrix(p)).t for p in
                                                               before["RA"]], atol=1e-3)
        finally:
            service.close()


class TestAdminActions:
    def test_a_robot_locked_out_by_its_largest_id_or_timestamp_is_reset(self, tmp_path):
        service = service_on(str(tmp_path / "fleet.sqlite"))
        try:
            for name in ("A", "B"):
                service.register(name)
            service.submit_keyframe("B", 0, 0.0, np.eye(4))  # the anchor: A may be dropped
            service.submit_keyframe("A", 2**53 - 1, 1.0, np.eye(4))
            with pytest.raises(ConfigError, match="not after its last"):
                service.submit_keyframe("A", 5, 2.0, np.eye(4))
            assert service.reset("A", keep_keyframes=False) == 1
            assert service.submit_keyframe("A", 0, 1e11, np.eye(4))  # ids start again; now the largest timestamp
            with pytest.raises(ConfigError, match="before its last"):
                service.submit_keyframe("A", 1, 5.0, np.eye(4))
            service.reset("A", keep_keyframes=False)
            assert service.submit_keyframe("A", 0, 5.0, np.eye(4))
            with pytest.raises(ConflictError, match="is the anchor"):
                service.reset("B", keep_keyframes=False)
        finally:
            service.close()

    def test_retire_and_rotate_tokens(self, tmp_path, caplog):
        service = service_on(str(tmp_path / "fleet.sqlite"))
        try:
            token = service.register("A")
            assert service.authenticate("A", token)
            service.submit_keyframe("A", 0, 0.0, np.eye(4))
            with caplog.at_level(logging.WARNING, "cae_lcd.fleet.service"):
                new = service.rotate_token("A")
                assert not service.authenticate("A", token) and service.authenticate("A", new)
                service.retire("A")  # keyframes kept
                assert not service.authenticate("A", new) and service.store.retired() == ["A"]
                assert [p["keyframe"] for p in service.poses("A", wait=True)] == [0]
                again = service.rotate_token("A")  # back in service
            assert service.authenticate("A", again) and service.store.retired() == []
            audit = [r.getMessage() for r in caplog.records if r.getMessage().startswith("admin:")]
            assert len(audit) == 3 and "retired" in audit[1]
        finally:
            service.close()
