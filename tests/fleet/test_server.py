"""cae_lcd.fleet.server, cae_lcd.fleet.client and cae_lcd.fleet.service through FastAPI's TestClient, with the bundled sample's real KITTI
JPEG frames and ground-truth poses."""

from __future__ import annotations

import numpy as np
import psycopg
import pytest

from cae_lcd.fleet.client import FleetClient, FleetError
from cae_lcd.fleet.server import create_app
from cae_lcd.fleet.sim3 import Sim3
from cae_lcd.fleet.store import EdgeRecord

ADMIN = "admin-secret"


@pytest.fixture
def server(tmp_path, cae_descriptor):
    """``server()`` -> (TestClient, admin FleetClient) over the state in ``tmp_path/state`` (reopened each call)."""
    from fastapi.testclient import TestClient

    apps = []

    def start(store=None):
        if apps:
            apps[-1].state.service.close()  # as a stopped server does: the robots' databases are released
        apps.append(create_app(tmp_path / "state", ADMIN, descriptor=cae_descriptor, store=store))
        http = TestClient(apps[-1])
        return http, FleetClient("", ADMIN, client=http)

    yield start
    if apps:
        apps[-1].state.service.close()


def submit(client, robot, frames, sample_poses, jpeg):
    return [client.submit_keyframe(robot, i, 0.1 * i, sample_poses[i], jpeg(i)) for i in frames]


class TestRegistration:
    def test_admin_registers_robots_with_their_own_tokens(self, server):
        http, admin = server()
        token = admin.register("A")
        assert token.startswith("A.") and len(token) > 40
        with pytest.raises(FleetError, match="409"):
            admin.register("A")
        with pytest.raises(FleetError, match="403"):
            FleetClient("", token, client=http).register("B")
        with pytest.raises(FleetError, match="401"):
            FleetClient("", "A.guess", client=http).register("B")
        with pytest.raises(FleetError, match="422: body.name: String should match pattern"):
            admin.register("no spaces allowed")


class TestKeyframes:
    def test_submit_then_read_corrected_poses(self, server, sample_poses, jpeg):
        http, admin = server()
        robot = FleetClient("", admin.register("A"), client=http)
        assert submit(robot, "A", range(5), sample_poses, jpeg) == [True] * 5
        assert not robot.submit_keyframe("A", 3, 0.1 * 3, sample_poses[3], jpeg(3))  # a retry
        poses = robot.poses("A", wait=True)
        assert sorted(poses) == list(range(5))
        np.testing.assert_allclose(poses[4][:3], sample_poses[4], atol=1e-5)  # the first robot's frame is global
        assert np.allclose(robot.transforms(wait=True)["A"], np.eye(4), atol=1e-6)

    def test_a_robot_writes_only_its_own_data(self, server, sample_poses, jpeg):
        http, admin = server()
        admin.register("A")
        b = FleetClient("", admin.register("B"), client=http)
        with pytest.raises(FleetError, match="404: no robot 'A'"):  # the same answer as for no robot at all
            b.submit_keyframe("A", 0, 0.0, sample_poses[0], jpeg(0))
        with pytest.raises(FleetError, match="404: no robot 'A'"):
            b.poses("A", wait=True)
        with pytest.raises(FleetError, match="404: no robot 'nobody'"):
            b.loops("nobody")

    @pytest.mark.parametrize("change, reason", [
        ({"image": b"not an image"}, "PNG or JPEG"),
        ({"pose": np.eye(3)}, "pose"),
        ({"pose": np.c_[2 * np.eye(3) + np.diag([0, 0, 1.0]), np.zeros(3)]}, "rotation"),
        ({"depth": np.zeros((10, 10))}, "depth must be"),
        ({"intrinsics": np.eye(4)}, "intrinsics"),
    ], ids=["image", "pose-shape", "pose-not-rigid", "depth-shape", "intrinsics"])
    def test_bad_keyframes_are_refused_with_one_line(self, server, sample_poses, jpeg, change, reason):
        http, admin = server()
        robot = FleetClient("", admin.register("A"), client=http)
        args = {"pose": sample_poses[0], "image": jpeg(0), **change}
        with pytest.raises(FleetError, match=reason):
            robot.submit_keyframe("A", 0, 0.0, **args)
        assert robot.poses("A", wait=True) == {}

    def test_a_depth_map_of_the_image_size_is_accepted(self, server, sample_poses, jpeg, sample_K):
        http, admin = server()
        robot = FleetClient("", admin.register("A"), client=http)
        assert robot.submit_keyframe("A", 0, 0.0, sample_poses[0], jpeg(0), sample_K, np.full((188, 620), 7.5))

    @pytest.mark.parametrize("backend", ["sqlite", "postgres"])
    def test_a_restarted_server_continues(self, server, sample_poses, jpeg, backend, request):
        url = request.getfixturevalue("local_postgres").create_database("restart") if backend == "postgres" else None
        http, admin = server(url)
        token = admin.register("A")
        submit(FleetClient("", token, client=http), "A", range(3), sample_poses, jpeg)
        if url:
            assert [r[0] for r in psycopg.connect(url).execute("SELECT keyframe FROM keyframes")] == [0, 1, 2]
        http, _ = server(url)  # a new app over the same state folder (and store)
        robot = FleetClient("", token, client=http)
        assert sorted(robot.poses("A", wait=True)) == [0, 1, 2]
        assert submit(robot, "A", [3], sample_poses, jpeg) == [True]
        with pytest.raises(FleetError, match="other content"):
            robot.submit_keyframe("A", 1, 0.0, sample_poses[2], jpeg(1))  # keyframe 1 again, another pose


class TestOverlapThroughTheService:
    def test_an_overlap_edge_merges_the_second_robot(self, server, sample_poses, jpeg, known_sim3):
        """B's poses are the sample's in B's own frame (``known_sim3`` maps them back); one overlap edge."""
        http, admin = server()
        a = FleetClient("", admin.register("A"), client=http)
        b = FleetClient("", admin.register("B"), client=http)
        submit(a, "A", range(0, 10, 2), sample_poses, jpeg)
        gt = [Sim3.from_pose(p) for p in sample_poses]
        for i in range(1, 10, 2):
            local = known_sim3.inverse().compose(gt[i])
            b.submit_keyframe("B", i, 0.1 * i, np.c_[local.R, local.t], jpeg(i))
        rel = gt[4].inverse().compose(known_sim3).compose(Sim3(1.0, *(lambda L: (L.R, L.t))(
            known_sim3.inverse().compose(gt[5]))))
        http.app.state.service.add_edge(EdgeRecord("overlap", "A", 4, "B", 5, rel, 40.0))
        T = Sim3.from_matrix(admin.transforms(wait=True)["B"])  # the fleet's list is the admin's
        angle, scale, trans = T.errors(known_sim3)
        assert angle < 0.1 and scale < 1e-3 and trans < 0.1
        assert [loop["kind"] for loop in b.loops("B")] == ["overlap"]
        np.testing.assert_allclose(b.poses("B", wait=True)[5][:3, 3], sample_poses[5][:, 3], atol=0.05)


class TestPoisonedState:
    def test_a_state_holding_poisoned_values_still_starts(self, server, sample_poses, jpeg, tmp_path, caplog):
        """What an older version stored from a garbage robot (issue 19): a keyframe whose rotation block is scaled
        by 1e100 and an odometry edge of scale inf; the server reports them, skips them and serves the rest."""
        import json
        import sqlite3

        http, admin = server()
        a = FleetClient("", admin.register("A"), client=http)
        submit(a, "A", range(3), sample_poses, jpeg)
        http.app.state.service.close()
        bad = np.vstack([sample_poses[3], [0, 0, 0, 1]])
        bad[:3, :3] *= 1e100
        inf = np.diag([np.inf, np.inf, np.inf, 1.0])
        with sqlite3.connect(tmp_path / "state" / "fleet.sqlite") as db:
            db.execute("INSERT INTO keyframes VALUES (?, ?, ?, ?)", ("A", 3, 0.3, json.dumps(bad.ravel().tolist())))
            for kind, ka, kb in (("odometry", 2, 3), ("loop", 0, 2)):
                db.execute("INSERT INTO edges (kind, robot_a, keyframe_a, robot_b, keyframe_b, sim3, score) VALUES "
                           "(?, ?, ?, ?, ?, ?, ?)", (kind, "A", ka, "A", kb, json.dumps(inf.ravel().tolist()), 1.0))
        http, admin = server()  # starts
        assert any("skipped" in r.getMessage() for r in caplog.records)
        assert sorted(admin.poses("A", wait=True)) == [0, 1, 2]
        assert admin.loops("A") == []  # the unloadable loop edge is left out, not a 500


class TestAdminRoutes:
    def test_only_the_admin_resets_retires_rotates_and_names_the_anchor(self, server, sample_poses, jpeg, caplog):
        http, admin = server()
        a = FleetClient("", admin.register("A"), client=http)
        b_token = admin.register("B")
        b = FleetClient("", b_token, client=http)
        submit(a, "A", range(3), sample_poses, jpeg)
        submit(b, "B", range(2), sample_poses, jpeg)
        for call in (lambda: a.reset("A"), lambda: a.retire("B"), lambda: a.rotate_token("A"),
                     lambda: a.set_anchor("B")):
            with pytest.raises(FleetError, match="403"):
                call()
        with pytest.raises(FleetError, match="404"):
            admin.reset("nobody")
        with caplog.at_level("WARNING", "cae_lcd.fleet.service"):
            assert admin.reset("A", keep_keyframes=True) == 0
            assert sorted(admin.poses("A", wait=True)) == [0, 1, 2]  # kept
            assert submit(a, "A", [3], sample_poses, jpeg) == [True]  # recognition from nothing, ids go on
            with pytest.raises(FleetError, match="409: robot 'A' is the anchor"):
                admin.reset("A", keep_keyframes=False)
            admin.set_anchor("B")
            assert admin.reset("A", keep_keyframes=False) == 4 and admin.poses("A", wait=True) == {}
            assert submit(a, "A", [0], sample_poses, jpeg) == [True]  # from the start again
            new = admin.rotate_token("B")
            with pytest.raises(FleetError, match="401"):
                FleetClient("", b_token, client=http).poses("B")
            b = FleetClient("", new, client=http)
            assert sorted(b.poses("B", wait=True)) == [0, 1]
            assert admin.retire("B") == 0
            with pytest.raises(FleetError, match="401"):
                b.poses("B")
            assert sorted(admin.poses("B", wait=True)) == [0, 1]  # its map stays
        audit = [r.getMessage() for r in caplog.records if r.getMessage().startswith("admin:")]
        assert len(audit) == 5, audit

    def test_a_robot_locked_out_by_id_2_53_minus_1_is_reset(self, server, sample_poses, jpeg):
        http, admin = server()
        z = FleetClient("", admin.register("Z"), client=http)
        z.submit_keyframe("Z", 0, 0.0, sample_poses[0], jpeg(0))  # the anchor (whose keyframes cannot be dropped)
        a = FleetClient("", admin.register("A"), client=http)
        assert a.submit_keyframe("A", 2**53 - 1, 1e11, sample_poses[0], jpeg(0))
        for keyframe, t in ((5, 1e11), (2**53 - 1, 1e11 + 1)):
            with pytest.raises(FleetError, match="400"):
                a.submit_keyframe("A", keyframe, t, sample_poses[1], jpeg(1))
        admin.reset("A", keep_keyframes=False)
        assert a.submit_keyframe("A", 0, 0.0, sample_poses[1], jpeg(1))


class TestWhatARobotReads:
    def test_a_robots_token_reads_its_own_transform_and_overlaps_the_admin_all(self, server, sample_poses, jpeg,
                                                                                known_sim3):
        from cae_lcd.fleet.store import OverlapRecord

        http, admin = server()
        robots = {n: FleetClient("", admin.register(n), client=http) for n in ("A", "B", "C")}
        submit(robots["A"], "A", range(0, 10, 2), sample_poses, jpeg)
        gt = [Sim3.from_pose(p) for p in sample_poses]
        for i in range(1, 10, 2):
            local = known_sim3.inverse().compose(gt[i])
            robots["B"].submit_keyframe("B", i, 0.1 * i, np.c_[local.R, local.t], jpeg(i))
        rel = gt[4].inverse().compose(known_sim3).compose(Sim3(1.0, *(lambda L: (L.R, L.t))(
            known_sim3.inverse().compose(gt[5]))))
        service = http.app.state.service
        service.add_edge(EdgeRecord("overlap", "A", 4, "B", 5, rel, 40.0))
        service.store.add_overlap(OverlapRecord("A", "B", known_sim3, 3, 1.0))
        assert sorted(admin.transforms(wait=True)) == ["A", "B"] and len(admin.overlaps()) == 1
        assert list(robots["A"].transforms(wait=True)) == ["A"] and list(robots["B"].transforms()) == ["B"]
        assert len(robots["A"].overlaps()) == len(robots["B"].overlaps()) == 1
        assert robots["C"].transforms() == {} and robots["C"].overlaps() == []  # no name of another robot leaks

    def test_the_schema_says_what_the_server_enforces(self, server, sample_poses, jpeg):
        """``"pose": [[], [], []]`` was schema-valid and answered 400 (schemathesis ST202): rows have their length
        in the schema now (422)."""
        import base64

        http, admin = server()
        token = admin.register("A")
        body = {"keyframe": 0, "timestamp": 0.0, "pose": [[], [], []], "image": base64.b64encode(jpeg(0)).decode()}
        answer = http.post("/robots/A/keyframes", json=body, headers={"Authorization": f"Bearer {token}"})
        assert answer.status_code == 422 and "at least 4" in answer.json()["detail"]
        rows = http.get("/openapi.json").json()["components"]["schemas"]["KeyframeIn"]["properties"]["pose"]["items"]
        assert rows["minItems"] == rows["maxItems"] == 4


class TestRefusals:
    def test_a_413_says_what_the_header_declares_in_one_sensible_line(self, server):
        """Pillow's own bomb limit gives a pixel count alone: the answer was "image has 900000000x1 pixels"."""
        import base64
        import struct
        import zlib

        import cv2

        http, admin = server()
        token = admin.register("A")
        png = bytearray(cv2.imencode(".png", np.zeros((8, 8), np.uint8))[1].tobytes())
        ihdr = bytes(png[12:16]) + struct.pack(">II", 30000, 30000) + bytes(png[24:29])
        png[12:33] = ihdr + struct.pack(">I", zlib.crc32(ihdr))
        body = {"keyframe": 0, "timestamp": 0.0, "pose": np.eye(4).tolist(), "image": base64.b64encode(png).decode()}
        answer = http.post("/robots/A/keyframes", json=body, headers={"Authorization": f"Bearer {token}"})
        assert answer.status_code == 413
        assert answer.json()["detail"].startswith("image too large: its header declares 900000000 pixels; at most")
