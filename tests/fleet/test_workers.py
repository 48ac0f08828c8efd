"""cae_lcd.fleet.workers: robots sharded over two Ray workers (one module-scoped local Ray, 2 CPUs) on real KITTI frames: the
overlap of two robots on different workers is found as in one process, and a killed worker's robots continue."""

from __future__ import annotations

import numpy as np
import pytest

from cae_lcd.core.cluster import start_ray
from cae_lcd.fleet.workers import NAMESPACE, RayRecognizer, create_recognizer, host_name, shard_of

from .conftest import FIXED

ray = pytest.importorskip("ray")

# A (KITTI 00 even frames) and B (odd frames) on different shards of 2 (checked below)
A, B = "C", "D"


@pytest.fixture(scope="module")
def local_ray():
    _, started = start_ray(cpus=2)
    yield
    if started:
        ray.shutdown()


def frames(kitti_sequences, kitti_poses, ids):
    import cv2

    from cae_lcd.fleet.sim3 import Sim3
    from retrieval.sequences import read_kitti_calib

    K = read_kitti_calib(kitti_sequences / "00" / "calib.txt")
    poses = kitti_poses("00")
    for i in ids:
        image = cv2.imread(str(kitti_sequences / "00" / "image_0" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        yield (A if i % 2 == 0 else B), i, Sim3.from_pose(poses[i]).matrix(), image, K


def process(rec, robot, i, pose, image, K):
    """What the service does: recognition, then (the keyframe stored) ``committed``."""
    found = rec.process(robot, i, float(i), pose, image, K)
    rec.committed(robot)
    return found


def test_robots_are_sharded_by_name():
    assert shard_of(A, 2) != shard_of(B, 2)
    assert [shard_of(f"r{i}", 4) for i in range(8)] == [shard_of(f"r{i}", 4) for i in range(8)]
    assert {shard_of(f"robot{i:02d}", 4) for i in range(32)} == {0, 1, 2, 3}


class Spy:
    """What the shards copy to each other (``adopt``), seen from the driver: the searched entries among it."""

    def __init__(self, rec: RayRecognizer) -> None:
        self.entries = 0
        self.keyframes = 0
        real = rec.committed

        def committed(robot: str) -> None:
            for _, kf in rec._pending.get(robot, []):
                self.keyframes += 1
                self.entries += kf.entry is not None
            real(robot)

        rec.committed = committed


@pytest.mark.parametrize("places", ["local", "milvus"])
def test_overlap_across_workers_and_a_killed_worker(local_ray, tmp_path, kitti_sequences, kitti_poses, places):
    """With ``milvus`` both workers search one collection (milvus-lite served by one more actor): each inserts its own
    robot's entries only, and nothing searched is copied between them; ``local``: each worker's own memory, every
    entry copied."""
    # one adopted keyframe's features kept per robot: the others' are fetched from their worker (cae_lcd.fleet.workers FETCH)
    rec = create_recognizer(tmp_path, {**FIXED, "adopted_features": 1, "places": {"name": places}}, workers=2)
    assert isinstance(rec, RayRecognizer) and rec.parallel_robots
    spy = Spy(rec)
    found = [process(rec, robot, i, pose, image, K)
             for robot, i, pose, image, K in frames(kitti_sequences, kitti_poses, range(100, 110))]
    overlaps = [o for r in found for o in r.overlaps]
    assert len(overlaps) == 1 and {overlaps[0].robot_a, overlaps[0].robot_b} == {A, B}
    edges = [e for r in found for e in r.edges if e.kind == "overlap"]
    assert edges and all({e.robot_a, e.robot_b} == {A, B} for e in edges)
    assert spy.keyframes >= 8 and spy.entries == (spy.keyframes if places == "local" else 0)

    ray.kill(rec._shards[shard_of(B, 2)])  # B's worker dies
    assert rec.has(B, 109) and not rec.has(B, 111)  # restarted: B's database reopened from the state folder
    later = [process(rec, robot, i, pose, image, K)
             for robot, i, pose, image, K in frames(kitti_sequences, kitti_poses, range(110, 116))]
    assert any(e.kind == "overlap" and e.robot_b == B for r in later for e in r.edges)  # B still matched with A
    if places == "milvus":  # one collection: every keyframe once, though B's restarted worker added B's again
        shared = connect(rec)
        assert len(shared) == spy.keyframes and (A, 100) in shared and (B, 115) in shared
        assert ray.get_actor(host_name(rec.state_dir), namespace=NAMESPACE)
        shared.close()
    rec.close()


def connect(rec: RayRecognizer):
    """The workers' Milvus place memory, from this process (the URI the host actor gave them)."""
    from cae_lcd.fleet.places import create_fleet_places, resolve_places
    from retrieval.descriptors import create_descriptor
    from retrieval.detector import resolve_conf

    return create_fleet_places(create_descriptor({"name": "cae"}), None, resolve_conf(),
                               resolve_places(rec.conf["places"]), rec.state_dir)


def test_two_replicas_over_http_on_postgresql_milvus_and_ray(local_ray, local_postgres, tmp_path, kitti_sequences,
                                                               kitti_poses):
    """Two front ends (uvicorn on loopback) on one PostgreSQL store and the same two Ray workers, the place memory on
    Milvus: A streams through one, B through the other, and either replica serves the overlap and both robots."""
    import cv2

    from cae_lcd.fleet.client import FleetClient
    from cae_lcd.fleet.runner import ServerThread
    from cae_lcd.fleet.server import create_app

    url = local_postgres.create_database("replicas")
    apps = [create_app(tmp_path, "admin", store=url, workers=2, recognition={**FIXED, "places": {"name": "milvus"}})
            for _ in range(2)]
    with ServerThread(apps[0]) as one, ServerThread(apps[1]) as two:
        tokens = {r: FleetClient(one.url, "admin").register(r) for r in (A, B)}
        for robot, i, pose, image, K in frames(kitti_sequences, kitti_poses, range(100, 110)):
            server = one if robot == A else two
            assert FleetClient(server.url, tokens[robot]).submit_keyframe(
                robot, i, float(i), pose, cv2.imencode(".png", image)[1].tobytes(), K)
        for server in (one, two):  # the store's overlaps: once, though both robots' workers accepted the pair
            overlaps = FleetClient(server.url, "admin").overlaps()
            assert len(overlaps) == 1 and {overlaps[0]["robot_a"], overlaps[0]["robot_b"]} == {A, B}
        assert len(FleetClient(two.url, tokens[B]).poses(B, wait=True)) == 5  # (one's graph has B's joined ones only)
