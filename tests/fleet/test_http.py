"""The fleet server over real HTTP on loopback (uvicorn in a thread on a free port, ``cae_lcd.fleet.runner.ServerThread``),
with the bundled sample's real KITTI JPEG frames: concurrent robots, tokens, and hostile input that must be refused
with a clear 4xx and leave the state as it was."""

from __future__ import annotations

import base64
import json
import threading

import cv2
import httpx
import numpy as np
import pytest

from cae_lcd.fleet.client import FleetClient
from cae_lcd.fleet.runner import ServerThread
from cae_lcd.fleet.server import create_app

ADMIN = "http-admin-secret"
LIMITS = {"limits": {"max_request_mb": 1.0, "max_image_pixels": 500_000}}
NPY = b"\x93NUMPY\x01\x00"


@pytest.fixture(scope="module")
def live(tmp_path_factory, cae_descriptor):
    """A server on a free loopback port with robots A and B registered: ``(url, state dir, {robot: token})``."""
    state = tmp_path_factory.mktemp("http_state")
    with ServerThread(create_app(state, ADMIN, LIMITS, descriptor=cae_descriptor)) as server:
        admin = FleetClient(server.url, ADMIN)
        yield server.url, state, {r: admin.register(r) for r in ("A", "B")}


def body(i, sample_poses, jpeg, K=None, **change):
    out = {"keyframe": i, "timestamp": 0.1 * i, "pose": sample_poses[i].tolist(),
           "image": base64.b64encode(jpeg(i)).decode()}
    if K is not None:
        out["intrinsics"] = np.asarray(K).tolist()
    out.update(change)
    return out


def state_of(state, robot):
    """What a refused request must not change: the robot's acknowledged keyframes and its database's bytes."""
    from cae_lcd.fleet.store import SQLiteStore

    store = SQLiteStore(state / "fleet.sqlite")
    try:
        acks = [(a.keyframe, a.timestamp) for a in store.keyframes(robot)]
    finally:
        store.close()
    h5 = state / "robots" / robot / "keyframes.h5"
    return acks, h5.read_bytes() if h5.exists() else b""


class TestConcurrentRobots:
    def test_two_robots_submit_at_once(self, live, sample_poses, jpeg, sample_K):
        url, _, tokens = live
        errors = []

        def run(robot, frames):
            client = FleetClient(url, tokens[robot])
            try:
                for i in frames:
                    assert client.submit_keyframe(robot, i, 0.1 * i, sample_poses[i], jpeg(i), sample_K)
            except Exception as err:  # noqa: BLE001 - reported below
                errors.append(err)

        threads = [threading.Thread(target=run, args=("A", range(0, 16, 2))),
                   threading.Thread(target=run, args=("B", range(1, 16, 2)))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert not errors
        a, b = FleetClient(url, tokens["A"]), FleetClient(url, tokens["B"])
        # the global frame is the map of the robot whose keyframe was acknowledged first (the stored anchor): it is
        # merged, the other one too once they overlap
        poses = {r: sorted(c.poses(r, wait=True)) for r, c in (("A", a), ("B", b))}
        assert poses["A"] in ([], list(range(0, 16, 2))) and poses["B"] in ([], list(range(1, 16, 2)))
        assert poses["A"] or poses["B"]
        assert set(a.transforms(wait=True)) <= {"A"} and set(b.transforms()) <= {"B"}  # each reads its own
        assert b.loops("B") == [] or {e["kind"] for e in b.loops("B")} <= {"loop", "overlap"}


class TestTokens:
    def test_no_token_is_401(self, live, sample_poses, jpeg):
        url = live[0]
        r = httpx.post(f"{url}/robots/A/keyframes", json=body(40, sample_poses, jpeg))
        assert r.status_code == 401 and "token" in r.json()["detail"]

    def test_a_forged_token_is_401(self, live, sample_poses, jpeg):
        url, _, tokens = live
        forged = "A." + tokens["B"].split(".", 1)[1]
        r = httpx.get(f"{url}/robots/A/poses", headers={"Authorization": f"Bearer {forged}"})
        assert r.status_code == 401

    def test_another_robots_id_is_the_same_404_as_no_robot(self, live, sample_poses, jpeg):
        url, state, tokens = live
        before = state_of(state, "A")
        r = httpx.post(f"{url}/robots/A/keyframes", json=body(40, sample_poses, jpeg),
                       headers={"Authorization": f"Bearer {tokens['B']}"})
        missing = httpx.post(f"{url}/robots/Z/keyframes", json=body(40, sample_poses, jpeg),
                             headers={"Authorization": f"Bearer {tokens['B']}"})
        assert r.status_code == missing.status_code == 404 and "robot 'A'" in r.json()["detail"]
        assert state_of(state, "A") == before


def _big_image(jpeg):
    image = cv2.imdecode(np.frombuffer(jpeg(0), np.uint8), cv2.IMREAD_UNCHANGED)
    return base64.b64encode(cv2.imencode(".png", cv2.resize(image, (1240, 564)))[1].tobytes()).decode()


def _huge_jpeg(jpeg, side=65500):
    """A few hundred bytes of a real JPEG whose header claims ``side`` x ``side`` pixels."""
    data = bytearray(jpeg(0))
    sof = data.find(b"\xff\xc0")
    data[sof + 5:sof + 9] = side.to_bytes(2, "big") * 2
    return base64.b64encode(bytes(data[:333])).decode()


def _npy(array=None, shape=None, dtype="<f8"):
    """A base64 .npy of ``array``, or a bare header declaring ``shape`` (no data)."""
    if array is not None:
        import io

        buf = io.BytesIO()
        np.save(buf, array, allow_pickle=False)
        return base64.b64encode(buf.getvalue()).decode()
    header = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode()
    header += b" " * (63 - (len(header) + 10) % 64) + b"\n"
    return base64.b64encode(NPY + len(header).to_bytes(2, "little") + header).decode()


def _scaled_pose(scale):
    p = np.eye(4)[:3]
    p[:, :3] *= scale
    return p.tolist()


BAD = {  # name -> (change to a good body, expected status, words of the reason)
    "not-an-image": (lambda j: {"image": base64.b64encode(b"GIF89a not an image").decode()}, 400, "PNG or JPEG"),
    "not-base64": (lambda j: {"image": "%%%"}, 400, "base64"),
    # rows of another length: the schema says it (422; issue 29: a 3x0 pose was schema-valid, then 400)
    "pose-shape": (lambda j: {"pose": np.eye(3).tolist()}, 422, "pose"),
    "pose-ragged": (lambda j: {"pose": [[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0]]}, 422, "pose"),
    "pose-nan": (lambda j: {"pose": [[float("nan")] * 4] * 3}, 400, "finite"),
    "timestamp-nan": (lambda j: {"timestamp": float("nan")}, 400, "timestamp"),
    "intrinsics-shape": (lambda j: {"intrinsics": np.eye(4).tolist()}, 422, "at most 3"),
    "intrinsics-nan": (lambda j: {"intrinsics": [[float("nan")] * 3] * 3}, 400, "intrinsics"),
    "negative-id": (lambda j: {"keyframe": -1}, 422, "keyframe"),
    "image-too-large": (lambda j: {"image": _big_image(j)}, 413, "pixels"),
    # the attacks of issue 19, each a 500, a silent acceptance or a blocked robot before
    "jpeg-header-65500": (lambda j: {"image": _huge_jpeg(j)}, 413, "pixels"),
    "jpeg-header-30000": (lambda j: {"image": _huge_jpeg(j, 30000)}, 413, "pixels"),
    "depth-header-huge": (lambda j: {"depth": _npy(shape=(100000, 100000))}, 400, "(100000, 100000)"),
    "depth-all-nan": (lambda j: {"depth": _npy(np.full((188, 620), np.nan, np.float32))}, 400, "finite"),
    "depth-negative": (lambda j: {"depth": _npy(np.full((188, 620), -1e30, np.float32))}, 400, "finite"),
    "id-2**63": (lambda j: {"keyframe": 2**63}, 422, "keyframe"),
    "id-2**63-1": (lambda j: {"keyframe": 2**63 - 1}, 422, "keyframe"),
    "id-1e30": (lambda j: {"keyframe": 1e30}, 422, "keyframe"),
    "id-as-string": (lambda j: {"keyframe": "40"}, 422, "keyframe"),
    "timestamp-as-string": (lambda j: {"timestamp": "4.0"}, 422, "timestamp"),
    "timestamp-1e300": (lambda j: {"timestamp": 1e300}, 400, "timestamp"),
    "timestamp-backwards": (lambda j: {"timestamp": 0.05}, 400, "before its last"),
    "pose-scaled-down": (lambda j: {"pose": _scaled_pose(1e-100)}, 400, "rotation"),
    "pose-scaled-up": (lambda j: {"pose": _scaled_pose(1e100)}, 400, "rotation"),
    "pose-far": (lambda j: {"pose": (np.c_[np.eye(3), [1e300, 0, 0]]).tolist()}, 400, "translation"),
    "intrinsics-zero": (lambda j: {"intrinsics": np.zeros((3, 3)).tolist()}, 400, "intrinsics"),
    "unknown-field": (lambda j: {"padding": "x" * 1000}, 422, "padding"),
    # a near-singular camera: with a depth map its back-projected points overflowed and hung the server
    "intrinsics-tiny-focal": (lambda j: {"intrinsics": [[1e-300, 0, 300], [0, 1e-300, 90], [0, 0, 1]]}, 400,
                              "fx and fy"),
}


class TestMalformedInput:
    @pytest.mark.parametrize("name", list(BAD))
    def test_refused_with_a_clear_4xx_and_the_state_untouched(self, live, sample_poses, jpeg, name):
        url, state, tokens = live
        change, status, words = BAD[name]
        before = state_of(state, "A")
        payload = json.dumps(body(40, sample_poses, jpeg, **change(jpeg)))  # NaN as JSON's common extension
        r = httpx.post(f"{url}/robots/A/keyframes", content=payload,
                       headers={"Authorization": f"Bearer {tokens['A']}", "Content-Type": "application/json"})
        assert r.status_code == status, r.text
        detail = r.json()["detail"]
        assert isinstance(detail, str) and "\n" not in detail and words in detail  # one line, schema errors too
        assert state_of(state, "A") == before

    def test_an_oversized_body_is_413(self, live, sample_poses, jpeg):
        url, state, tokens = live
        before = state_of(state, "A")
        padded = body(40, sample_poses, jpeg, image=base64.b64encode(b"\0" * 1_200_000).decode())
        r = httpx.post(f"{url}/robots/A/keyframes", json=padded, headers={"Authorization": f"Bearer {tokens['A']}"})
        assert r.status_code == 413 and "bytes" in r.json()["detail"]
        assert state_of(state, "A") == before

    def test_a_retry_with_another_image_is_409_and_the_same_retry_200(self, live, sample_poses, jpeg):
        url, state, tokens = live
        before = state_of(state, "A")
        auth = {"Authorization": f"Bearer {tokens['A']}"}
        same = httpx.post(f"{url}/robots/A/keyframes", json=body(14, sample_poses, jpeg, timestamp=0.1 * 14), headers=auth)
        assert same.status_code == 200 and same.json()["stored"] is False
        other = body(14, sample_poses, jpeg, timestamp=1.4, image=base64.b64encode(jpeg(15)).decode())
        r = httpx.post(f"{url}/robots/A/keyframes", json=other, headers=auth)
        assert r.status_code == 409 and "another image" in r.json()["detail"]
        assert state_of(state, "A") == before

    def test_a_retry_with_other_intrinsics_is_409(self, live, sample_poses, jpeg, sample_K):
        url, state, tokens = live
        auth = {"Authorization": f"Bearer {tokens['A']}"}
        httpx.post(f"{url}/robots/A/keyframes", json=body(14, sample_poses, jpeg, sample_K), headers=auth)
        before = state_of(state, "A")
        other = body(14, sample_poses, jpeg, np.diag([2.0, 2.0, 1.0]) @ sample_K)
        r = httpx.post(f"{url}/robots/A/keyframes", json=other, headers=auth)
        assert r.status_code == 409 and "other intrinsics" in r.json()["detail"]  # was 200, stored: false
        same = httpx.post(f"{url}/robots/A/keyframes", json=body(14, sample_poses, jpeg, sample_K), headers=auth)
        assert same.status_code == 200 and same.json()["stored"] is False
        assert state_of(state, "A") == before

    @pytest.mark.parametrize("change", [{f"k{i}": 0 for i in range(600)}, {"pose": [["x"] * 300] * 3}],
                             ids=["600-unknown-fields", "pose-rows-of-300-strings"])
    def test_many_bad_values_get_a_short_answer(self, live, sample_poses, jpeg, change):
        """One error a bad value made a 2 MB body of unknown keys a 180 MB answer (40 s, 3.7 GB of memory)."""
        url, state, tokens = live
        before = state_of(state, "A")
        r = httpx.post(f"{url}/robots/A/keyframes", json=body(40, sample_poses, jpeg, **change),
                       headers={"Authorization": f"Bearer {tokens['A']}"})
        assert r.status_code == 422 and len(r.json()["errors"]) <= 20 and len(r.content) < 5000, r.text[:300]
        assert "\n" not in r.json()["detail"]
        assert state_of(state, "A") == before

    def test_a_refused_first_keyframe_leaves_no_trace(self, live, sample_poses, jpeg, sample_K):
        url, state, _ = live
        token = FleetClient(url, ADMIN).register("D")
        tiny = base64.b64encode(cv2.imencode(".png", np.zeros((1, 1), np.uint8))[1].tobytes()).decode()
        r = httpx.post(f"{url}/robots/D/keyframes", json=body(0, sample_poses, jpeg, sample_K, image=tiny),
                       headers={"Authorization": f"Bearer {token}"})
        assert r.status_code == 400 and "too small" in r.json()["detail"]
        assert not (state / "robots" / "D" / "camera.json").exists()
        assert FleetClient(url, token).submit_keyframe("D", 0, 0.0, sample_poses[0], jpeg(0), sample_K)

    def test_a_depth_map_without_intrinsics_is_refused(self, live, sample_poses, jpeg, sample_K):
        """It was acknowledged and dropped without a word (no camera to back-project it with)."""
        url, state, _ = live
        token = FleetClient(url, ADMIN).register("E")
        depth = _npy(np.full((188, 620), 5.0, np.float32))
        r = httpx.post(f"{url}/robots/E/keyframes", json=body(0, sample_poses, jpeg, depth=depth),
                       headers={"Authorization": f"Bearer {token}"})
        assert r.status_code == 400 and "needs intrinsics" in r.json()["detail"]
        assert not (state / "robots" / "E").exists() and state_of(state, "E") == ([], b"")
        r = httpx.post(f"{url}/robots/E/keyframes", json=body(0, sample_poses, jpeg, sample_K, depth=depth),
                       headers={"Authorization": f"Bearer {token}"})
        assert r.status_code == 200 and r.json()["stored"] is True

    def test_an_unknown_robot_is_404(self, live, sample_poses, jpeg):
        url, state, _ = live
        r = httpx.post(f"{url}/robots/C/keyframes", json=body(40, sample_poses, jpeg),
                       headers={"Authorization": f"Bearer {ADMIN}"})
        assert r.status_code == 404 and "no robot 'C'" in r.json()["detail"]
        assert not (state / "robots" / "C").exists()

    def test_a_good_keyframe_after_the_refusals_is_stored(self, live, sample_poses, jpeg, sample_K):
        url, state, tokens = live
        assert FleetClient(url, tokens["A"]).submit_keyframe("A", 40, 4.0, sample_poses[40], jpeg(40), sample_K)
        assert state_of(state, "A")[0][-1] == (40, 4.0)
