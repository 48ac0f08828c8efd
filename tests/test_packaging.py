"""Packaging: the wheel builds without setuptools' licence deprecation warning, holds the code, the shipped weights
and sample, declares the extras (the detector alone needs no fleet, Ray or ROS package), and works once installed.

Cheap: the wheel is built without build isolation (no download) and installed with ``--no-deps`` into a folder that
the interpreter that already has the dependencies puts first on its path.
"""

from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("wheel")
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", str(out),
                            str(REPO)], capture_output=True, text=True, timeout=300, cwd=out)
    assert build.returncode == 0, build.stderr[-2000:]
    return next(out.glob("cae_loop_closure-*.whl")), build.stdout + build.stderr


def test_no_licence_deprecation_warning(wheel):
    assert not [ln for ln in wheel[1].lower().splitlines() if "licen" in ln and "deprecat" in ln]


def test_contents_and_extras(wheel):
    with zipfile.ZipFile(wheel[0]) as z:
        names = set(z.namelist())
        meta = next(z.read(n).decode() for n in names if n.endswith(".dist-info/METADATA"))
    assert {"cli/main.py", "retrieval/sequences/rosbag.py", "retrieval/batch.py", "core/progress.py",
            "retrieval/sample/loops.txt", "retrieval/sample/image_0/000099.jpg"} <= names
    assert any(n.startswith("cae/weights/") and n.endswith(".pt") for n in names)
    assert not any(n.startswith("tests/") for n in names)
    assert "License-Expression: MIT" in meta
    requires = [ln.split(":", 1)[1].strip() for ln in meta.splitlines() if ln.startswith("Requires-Dist:")]
    for extra, package in (("fleet", "fastapi"), ("fleet", "gtsam"), ("ray", "ray"), ("ros", "rosbags")):
        assert f"Provides-Extra: {extra}" in meta
        assert all(f'extra == "{extra}"' in r for r in requires if r.split(">")[0].split("[")[0].strip() == package)


def test_installed_wheel_runs(wheel, tmp_path):
    site = tmp_path / "site"
    install = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-compile", "--target",
                              str(site), str(wheel[0])], capture_output=True, text=True, timeout=300)
    assert install.returncode == 0, install.stderr[-2000:]
    code = ("import cli.main, cae, retrieval.detect as d; "
            "assert cli.main.__file__.startswith(%r), cli.main.__file__; "
            "assert len(list((d.SAMPLE_DIR / 'image_0').glob('*.jpg'))) == 100; "
            "cae.load_encoder(device='cpu'); raise SystemExit(cli.main.main(['--version']))" % str(site))
    env = {**os.environ, "PYTHONPATH": str(site)}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=tmp_path,
                         env=env)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.strip() == "cae-lcd 0.1.0"


def test_detector_needs_no_optional_extra(tmp_path):
    """With the fleet's, Ray's and ROS's packages absent, the CLI loads, ``detect`` parses, ``serve`` says why not."""
    code = """
import importlib.abc, sys
class Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in {"fastapi", "uvicorn", "httpx", "gtsam", "ray", "rosbags", "starlette", "pydantic"}:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Absent())
from cli.main import main
assert main(["detect", "--help"]) == 0
assert main(["serve", "--state", "x"]) == 2
assert not {"fastapi", "gtsam", "ray", "rosbags", "httpx"} & set(sys.modules)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "cae-lcd serve needs the 'fleet' extra (fastapi is not installed)" in run.stderr
