"""``cae-lcd bench`` runs from the checkout's root without PYTHONPATH (``bench/`` is not installed: ``make bench``),
and says so in one line anywhere else."""

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _bench_help(cwd: Path) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    script = Path(sys.executable).with_name("cae-lcd")  # the installed script: its sys.path holds no checkout
    return subprocess.run([str(script), "bench", "--help"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_bench_runs_from_the_checkout_root():
    run = _bench_help(REPO)
    assert run.returncode == 0 and "--training-study" in run.stdout


def test_bench_elsewhere_says_it_needs_the_checkout(tmp_path):
    run = _bench_help(tmp_path)
    assert run.returncode != 0 and "checkout of the repository" in run.stdout + run.stderr
