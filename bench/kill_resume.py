"""Kill ``cae-lcd detect`` with SIGKILL at random moments, run it again, and compare with an uninterrupted run:
``python -m bench.kill_resume [PATH] [--moments 50]``.

Each trial starts a fresh run in a subprocess, kills it (``kill -9``) after a random delay drawn over the length of
a whole run, then runs the same command to the end (it resumes from ``keyframes.h5``). The trial passes when
``loops.csv`` and ``candidates.csv`` are byte-identical to the uninterrupted run's.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from retrieval.detect import SAMPLE_DIR
from retrieval.run_folder import RunFolder

__all__ = ["main"]

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]


def _detect(path: Path, out: Path, config: Path | None) -> subprocess.Popen:
    args = [sys.executable, "-m", "cae_lcd.cli.main", "detect", str(path), "--out", str(out), "--no-progress"]
    args += ["--config", str(config)] if config is not None else []
    return subprocess.Popen(args, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _tables(out: Path) -> tuple[bytes, bytes]:
    run = RunFolder(out)
    return run.loops.read_bytes(), run.candidates.read_bytes()


def main(path: str | Path | None = None, out: str | Path = "runs/bench/kill_resume", moments: int = 50,
         seed: int = 0, config: str | Path | None = None) -> dict[str, Any]:
    """Runs the trials and returns ``{"moments", "identical", "killed_mid_run", "failures", "run_s"}``.

    Args:
        path: sequence folder; None = the bundled sample.
        out: working folder (rewritten).
        moments: number of kill-and-resume trials.
        seed: seeds the kill delays.
        config: detector config file passed to every run.
    """
    path = Path(path) if path is not None else SAMPLE_DIR
    out = Path(out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    cfg = Path(config) if config is not None else None
    t0 = time.perf_counter()
    ref = _detect(path, out / "reference", cfg)
    if ref.wait() != 0:
        raise RuntimeError(f"reference run failed: {ref.stderr.read()[-500:]}")
    run_s = time.perf_counter() - t0
    reference = _tables(out / "reference")
    rng = np.random.default_rng(seed)
    identical, mid_run, failures = 0, 0, []
    for trial in range(moments):
        target = out / "trial"
        shutil.rmtree(target, ignore_errors=True)
        proc = _detect(path, target, cfg)
        time.sleep(float(rng.uniform(0.0, run_s)))
        if proc.poll() is None:
            mid_run += 1
            proc.send_signal(signal.SIGKILL)
        proc.wait()
        resumed = _detect(path, target, cfg)
        code = resumed.wait()
        same = code == 0 and _tables(target) == reference
        identical += same
        if not same:
            failures.append({"trial": trial, "exit": code, "stderr": resumed.stderr.read()[-300:]})
            log.warning("trial %d: resumed run differs (exit %d)", trial, code)
    return {"moments": moments, "identical": identical, "killed_mid_run": mid_run, "failures": failures,
            "run_s": run_s}


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(prog="python -m bench.kill_resume", description=__doc__.split("\n\n")[0])
    ap.add_argument("path", nargs="?", help="sequence folder (default: the bundled sample)")
    ap.add_argument("--out", default="runs/bench/kill_resume")
    ap.add_argument("--moments", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config")
    res = main(args.path if (args := ap.parse_args()) else None, args.out, args.moments, args.seed, args.config)
    print(f"{res['identical']} of {res['moments']} killed runs resumed to identical tables "
          f"({res['killed_mid_run']} killed while running; an uninterrupted run takes {res['run_s']:.1f} s)")
    sys.exit(0 if res["identical"] == res["moments"] else 1)
