"""The live map page (``GET /map``, ``cae_lcd.fleet.map_page``) over the state of a real fleet demo: the page is
self-contained, the JSON routes it polls exist and give what it reads, the trajectory route serves the corrected
poses, and in headless Chromium (skipped where it is not installed) it draws what the API holds."""

from __future__ import annotations

import re
import shutil
import subprocess

import httpx
import numpy as np
import pytest

from bench.fleet_map import chromium_command, screenshot
from cae_lcd.fleet.client import FleetClient
from cae_lcd.fleet.export import format_trajectory
from cae_lcd.fleet.map_page import MAP_ROUTES
from cae_lcd.fleet.runner import ServerThread
from cae_lcd.fleet.demo import DEMO_RECOGNITION
from cae_lcd.fleet.server import create_app

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


@pytest.fixture(scope="module")
def served(fleet_demo_run, cae_descriptor):
    """The demo's state served again: ``(url, admin token, robot tokens {name: token})``."""
    out, _, token = fleet_demo_run
    app = create_app(out / "state", token, recognition=DEMO_RECOGNITION, descriptor=cae_descriptor)  # the demo's conf
    with ServerThread(app) as server:
        admin = FleetClient(server.url, token)
        admin.transforms(wait=True)
        yield server.url, token, {"C": admin.register("C")}


def get(url: str, path: str, token: str, **params) -> httpx.Response:
    return httpx.get(url + path, headers={"Authorization": f"Bearer {token}"}, params=params, timeout=60)


def test_the_page_needs_no_token_and_nothing_from_outside(served):
    url, _, _ = served
    r = httpx.get(url + "/map", timeout=30)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    html = r.text
    assert "<script src" not in html and "<link" not in html and "@import" not in html
    assert set(re.findall(r"https?://[^\s\"'<>]+", html)) <= {"http://www.w3.org/2000/svg"}  # a namespace only
    for path in MAP_ROUTES.values():
        assert path in html


def test_the_routes_the_page_polls_give_what_it_reads(served):
    url, token, _ = served
    spec = httpx.get(url + "/openapi.json", timeout=30).json()["paths"]
    for path in MAP_ROUTES.values():
        assert "get" in spec[path], path
    transforms = get(url, MAP_ROUTES["transforms"], token).json()
    assert set(transforms) == {"A", "B"}
    assert all({"robot_a", "robot_b"} <= set(o) for o in get(url, MAP_ROUTES["overlaps"], token).json())
    for name in transforms:
        poses = get(url, MAP_ROUTES["poses"].format(name=name), token).json()
        assert poses and all(np.shape(p["pose"]) == (4, 4) and isinstance(p["keyframe"], int) for p in poses)
        edges = get(url, MAP_ROUTES["loops"].format(name=name), token).json()
        assert all(e["kind"] in ("loop", "overlap") and len(e["a"]) == len(e["b"]) == 2 for e in edges)


def test_the_trajectory_route_serves_the_corrected_poses(served):
    url, token, robots = served
    poses = get(url, "/robots/B/poses", token).json()
    for fmt in ("tum", "kitti"):
        text = get(url, "/robots/B/trajectory", token, format=fmt).text
        rows = np.loadtxt(text.splitlines())
        assert rows.shape == (len(poses), 8 if fmt == "tum" else 12)
    kitti = np.loadtxt(get(url, "/robots/B/trajectory", token, format="kitti").text.splitlines())
    assert np.allclose(kitti.reshape(-1, 3, 4), np.array([p["pose"] for p in poses])[:, :3], atol=1e-6)
    assert format_trajectory(np.zeros(0), np.zeros((0, 4, 4)), "tum") == ""
    assert get(url, "/robots/B/trajectory", token, format="g2o").status_code == 422
    assert get(url, "/robots/B/trajectory", robots["C"]).status_code == 404  # not yours: the same 404 as no such robot
    assert get(url, "/robots/B/trajectory", "wrong").status_code == 401
    assert get(url, "/robots/Z/trajectory", token).status_code == 404


@pytest.mark.skipif(CHROMIUM is None, reason="no chromium (apt-get install -y chromium)")
def test_headless_chromium_draws_what_the_api_holds(served, tmp_path):
    url, token, _ = served
    page = f"{url}/map#token={token}"
    dom = subprocess.run(chromium_command(tmp_path / "profile") + ["--dump-dom", page], capture_output=True,
                         text=True, timeout=120).stdout
    status = dict(re.findall(r'data-(\w+)="(\d+)"', re.search(r'<div id="status"[^>]*>', dom).group(0)))
    poses = {n: get(url, MAP_ROUTES["poses"].format(name=n), token).json() for n in ("A", "B")}
    assert int(status["polls"]) >= 1 and int(status["robots"]) == 2
    assert int(status["keyframes"]) == sum(len(p) for p in poses.values())
    for name, p in poses.items():
        assert re.search(rf'<g id="robot-{name}" data-keyframes="{len(p)}"', dom)
    overlap_edges = {tuple(map(tuple, (e["a"], e["b"]))) for e in get(url, "/robots/B/loops", token).json()
                     if e["kind"] == "overlap"}
    assert int(status["overlaps"]) == len(overlap_edges) > 0
    shot = screenshot(page, tmp_path / "map.png")
    assert shot.stat().st_size > 10_000


def test_the_trajectory_route_documents_text_and_json_refusals(tmp_path):
    """The trajectory is plain text; its refusals are JSON like every route's (what schemathesis checks at random)."""
    responses = create_app(tmp_path, "a" * 24).openapi()["paths"]["/robots/{name}/trajectory"]["get"]["responses"]
    assert "text/plain" in responses["200"]["content"]
    assert all(list(r["content"]) == ["application/json"] for code, r in responses.items() if code != "200")
    assert {"401", "404", "422", "429"} <= set(responses)
