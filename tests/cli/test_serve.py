"""``cae-lcd serve``: the admin token's sources, one-line errors, and a real server process killed with SIGKILL in
the middle of two robots' streams of real KITTI 00 frames, then restarted: no acknowledged keyframe is lost and the
robots' overlap is still found."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cae_lcd.cli.main import main
from cae_lcd.cli.serve import TOKEN_ENV, admin_token
from cae_lcd.fleet.client import FleetClient, FleetError
from cae_lcd.fleet.demo import DEMO_TRUTH
from cae_lcd.fleet.recognition import FIXED_POLICY
from cae_lcd.fleet.sim3 import Sim3

REPO = Path(__file__).resolve().parents[2]
ADMIN = "serve-admin-secret"


class TestAdminToken:
    def test_given_then_environment_then_generated(self, monkeypatch):
        monkeypatch.setenv(TOKEN_ENV, "from-env")
        assert admin_token("given") == ("given", False)
        assert admin_token(None) == ("from-env", False)
        monkeypatch.delenv(TOKEN_ENV)
        token, generated = admin_token(None)
        assert generated and len(token) >= 32 and token != admin_token(None)[0]


class TestServeCommand:
    @pytest.mark.parametrize("args, words", [(["--port", "70000"], "--port"), (["--config", "missing.yaml"], "missing")])
    def test_bad_arguments_fail_with_one_line(self, tmp_path, capsys, args, words):
        code = main(["serve", "--state", str(tmp_path / "state"), *args])
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err
        assert [line for line in err.splitlines() if line.startswith("error: ") and words in line]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(state: Path, port: int, store: str | None = None) -> subprocess.Popen:
    """``cae-lcd serve`` in its own process (admin token from the environment, ``--store`` when given; the fixed
    policy, ``--config``: 15 keyframes a robot are within an online warm-up); returns once it answers."""
    env = {**os.environ, TOKEN_ENV: ADMIN}
    config = state.parent / "fixed_policy.yaml"
    config.write_text(json.dumps({"recognition": FIXED_POLICY}))  # JSON is YAML
    proc = subprocess.Popen([sys.executable, "-m", "cae_lcd.cli.main", "serve", "--state", str(state), "--port", str(port),
                             "--config", str(config)] + (["--store", store] if store else []),
                            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    admin = FleetClient(f"http://127.0.0.1:{port}", ADMIN, timeout=5)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            admin.overlaps()
            return proc
        except (FleetError, OSError, Exception):  # noqa: BLE001 - not listening yet
            if proc.poll() is not None:
                raise AssertionError(proc.stderr.read().decode())
            time.sleep(0.2)
    proc.kill()
    raise AssertionError("the server did not start")


@pytest.fixture(scope="module")
def frames(kitti_sequences):
    """Robot -> [(keyframe, pose, PNG bytes)]: A the even frames 100-129 of 00, B the odd ones in another map."""
    from retrieval.sequences import read_kitti_calib, read_kitti_poses

    P = read_kitti_poses(kitti_sequences.parent / "poses" / "00.txt")
    known_sim3 = DEMO_TRUTH
    unit = Sim3(1 / known_sim3.s, np.eye(3), np.zeros(3))
    out = {"A": [], "B": []}
    for i in range(100, 130):
        robot = "A" if i % 2 == 0 else "B"
        pose = Sim3.from_pose(P[i]) if robot == "A" else known_sim3.compose(Sim3.from_pose(P[i])).compose(unit)
        out[robot].append((i, pose.matrix(), (kitti_sequences / "00" / "image_0" / f"{i:06d}.png").read_bytes()))
    return out, read_kitti_calib(kitti_sequences / "00" / "calib.txt")


def stream(url, token, robot, frames, K, acked, stop_after=None, retries=0, errors=None):
    """Submits ``frames`` in order; records what the server acknowledged; stops at the first error (the server was
    killed), or tries a refused keyframe again up to ``retries`` times, 1 s apart, as a robot would (a server just
    restarted, on a loaded machine), keeping each error in ``errors``."""
    client = FleetClient(url, token, timeout=60)
    for i, pose, png in frames:
        for attempt in range(retries + 1):
            try:
                stored = client.submit_keyframe(robot, i, float(i), pose, png, K)
                break
            except Exception as err:  # noqa: BLE001 - the server was killed, or refused this once
                if errors is not None:
                    errors.append(f"{robot} {i}: {err}")
                if attempt == retries:
                    return
                time.sleep(1.0)
        acked.append((robot, i, stored))


class TestKillAndRestart:
    @pytest.mark.parametrize("backend", ["sqlite", "postgres"])
    def test_no_acknowledged_keyframe_is_lost_and_detection_continues(self, tmp_path, frames, backend, request):
        frames, K = frames
        port, state = free_port(), tmp_path / "state"
        url = f"http://127.0.0.1:{port}"
        store = request.getfixturevalue("local_postgres").create_database("serve") if backend == "postgres" else None
        proc = start_server(state, port, store)
        try:
            admin = FleetClient(url, ADMIN)
            tokens = {r: admin.register(r) for r in ("A", "B")}
            acked: list = []
            threads = [threading.Thread(target=stream, args=(url, tokens[r], r, frames[r], K, acked)) for r in "AB"]
            for t in threads:
                t.start()
            while len(acked) < 8:
                time.sleep(0.01)
            os.kill(proc.pid, signal.SIGKILL)  # mid-stream: requests are in flight
            proc.wait()
            for t in threads:
                t.join()
            before = {(r, i) for r, i, _ in acked}
            proc = start_server(state, port, store)
            again: list = []
            errors: list = []
            for r in "AB":
                stream(url, tokens[r], r, frames[r], K, again, retries=3, errors=errors)
            assert len(again) == 30, errors
            retried = {(r, i) for r, i, stored in again if not stored}
            assert before <= retried  # every acknowledged keyframe was still there: a retry, not stored again
            overlaps = admin.overlaps()
            assert overlaps and {overlaps[0]["robot_a"], overlaps[0]["robot_b"]} == {"A", "B"}
            assert sorted(FleetClient(url, tokens["A"]).poses("A", wait=True)) == list(range(100, 130, 2))
        finally:
            proc.kill()
            proc.wait()
