"""Packaging: the wheel builds without setuptools' licence deprecation warning, holds the code, the shipped weights
and sample (not bench/ nor tests/), declares the extras (the detector alone needs no fleet, Ray or ROS package), and
works once installed in a fresh virtual environment: beside a user's own ``core/`` package (the base layer lives
under the ``cae_lcd`` namespace), and with ``--config paper`` outside the repository.

Cheap and offline: the wheel is built without build isolation and installed with ``--no-deps --no-index``; the
dependencies come from this interpreter's site-packages.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> tuple[Path, str]:
    out = tmp_path_factory.mktemp("wheel")
    src = out / "src"  # a clean copy: a build/ left in the checkout by an earlier build would go into the wheel
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "dist", "runs", "*.egg-info",
                                                            "__pycache__", ".pytest_cache"))
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-w", str(out),
                            str(src)], capture_output=True, text=True, timeout=300, cwd=out)
    assert build.returncode == 0, build.stderr[-2000:]
    return next(out.glob("cae_loop_closure-*.whl")), build.stdout + build.stderr


def test_no_licence_deprecation_warning(wheel):
    assert not [ln for ln in wheel[1].lower().splitlines() if "licen" in ln and "deprecat" in ln]


def test_contents_and_extras(wheel):
    with zipfile.ZipFile(wheel[0]) as z:
        names = set(z.namelist())
        meta = next(z.read(n).decode() for n in names if n.endswith(".dist-info/METADATA"))
    assert {"cae_lcd/cli/main.py", "retrieval/sequences/rosbag.py", "retrieval/batch.py", "cae_lcd/core/progress.py",
            "retrieval/sample/loops.txt", "retrieval/sample/image_0/000099.jpg"} <= names
    assert any(n.startswith("cae/weights/") and n.endswith(".pt") for n in names)
    assert not any(n.startswith(("tests/", "bench/")) for n in names)
    assert "License-Expression: MIT" in meta
    requires = [ln.split(":", 1)[1].strip() for ln in meta.splitlines() if ln.startswith("Requires-Dist:")]
    for extra, package in (("fleet", "fastapi"), ("fleet", "gtsam"), ("ray", "ray"), ("ros", "rosbags")):
        assert f"Provides-Extra: {extra}" in meta
        assert all(f'extra == "{extra}"' in r for r in requires if r.split(">")[0].split("[")[0].strip() == package)


@pytest.fixture(scope="module")
def fresh_venv(wheel, tmp_path_factory) -> Path:
    """A new virtual environment holding the built wheel alone (``pip install --no-deps --no-index``); the
    dependencies (torch, numpy, ...) come from this interpreter's site-packages, named in a ``.pth`` file as a plain
    path (so the editable install of the checkout there, a ``.pth`` finder of its own, is not seen)."""
    venv = tmp_path_factory.mktemp("venv") / "v"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    own = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                         capture_output=True, text=True, check=True).stdout.strip()
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
                              "--no-index", "--no-compile", str(wheel[0])], capture_output=True, text=True, timeout=300,
                             env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert install.returncode == 0 and (Path(own) / "cae").is_dir(), install.stdout[-1000:] + install.stderr[-2000:]
    deps = [p for p in sys.path if p.endswith("site-packages")]  # after the install: pip would see the checkout's
    Path(own, "shared_deps.pth").write_text("\n".join(deps) + "\n")
    return venv


def _in_venv(venv: Path, args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "CAE_LCD_DEBUG")}
    return subprocess.run(args, capture_output=True, text=True, timeout=300, cwd=cwd, env=env)


def test_installed_wheel_runs(fresh_venv, tmp_path):
    """The installed package, not the checkout: the sample and weights ship, ``cae-lcd --version`` answers, and
    ``cae-lcd bench`` says that it runs in a checkout (bench/ is not installed)."""
    code = ("import cae, retrieval.detect as d; "
            "assert 'site-packages' in d.__file__, d.__file__; "
            "assert len(list((d.SAMPLE_DIR / 'image_0').glob('*.jpg'))) == 100; "
            "cae.load_encoder(device='cpu')")
    run = _in_venv(fresh_venv, [str(fresh_venv / "bin" / "python"), "-c", code], tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    version = _in_venv(fresh_venv, [str(fresh_venv / "bin" / "cae-lcd"), "--version"], tmp_path)
    assert version.returncode == 0 and version.stdout.strip() == "cae-lcd 0.1.0", version.stderr[-2000:]
    bench = _in_venv(fresh_venv, [str(fresh_venv / "bin" / "cae-lcd"), "bench"], tmp_path)
    assert bench.returncode == 2 and "cae-lcd bench runs in a checkout of the repository" in bench.stderr


def test_import_beside_a_users_own_core(fresh_venv, tmp_path):
    """A project with its own ``core/`` package (the wheel installed a top-level ``core`` before: ``import cae``
    failed with No module named 'core.errors')."""
    (tmp_path / "core").mkdir()
    (tmp_path / "core" / "__init__.py").write_text("mine = True\n")
    code = "import core, cae, retrieval.detect, verify; assert core.mine; cae.load_encoder(device='cpu')"
    run = _in_venv(fresh_venv, [str(fresh_venv / "bin" / "python"), "-c", code], tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]


def test_detect_with_a_preset_outside_the_repository(fresh_venv, tmp_path, copy_sample_frames):
    """``cae-lcd detect PATH --config paper`` from a folder that has no ``configs/``: the preset ships inside the
    package."""
    copy_sample_frames(range(20), tmp_path / "seq")
    run = _in_venv(fresh_venv, [str(fresh_venv / "bin" / "cae-lcd"), "detect", "seq", "--config", "paper", "--out",
                                "run", "--no-progress"], tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    conf = (tmp_path / "run" / "conf.yaml").read_text()
    assert "min_matches: 5" in conf and "model: none" in conf  # the paper's literal rule


def test_detector_needs_no_optional_extra(tmp_path):
    """With the fleet's, Ray's and ROS's packages absent, the CLI loads, ``detect`` parses, ``serve`` says why not."""
    code = """
import importlib.abc, sys
class Absent(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in {"fastapi", "uvicorn", "httpx", "gtsam", "ray", "rosbags", "starlette", "pydantic"}:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Absent())
from cae_lcd.cli.main import main
assert main(["detect", "--help"]) == 0
assert main(["serve", "--state", "x"]) == 2
assert not {"fastapi", "gtsam", "ray", "rosbags", "httpx"} & set(sys.modules)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "cae-lcd serve needs the 'fleet' extra (fastapi is not installed)" in run.stderr
