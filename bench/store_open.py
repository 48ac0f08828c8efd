"""Opening a large keyframe store to resume: ``python -m bench.store_open --keyframes 100000``.

Writes a store of ``--keyframes`` keyframes (256-d float16 codes, ``--features`` SIFT-like features each, one
candidate row, a pose and a time, as ``detect`` writes them), then times, in a fresh ``KeyframeDatabase``, what a
resume reads: opening (header, per-frame index columns, cutting a half-written tail) and every code and
candidate row with its checksum verified. The target: <= 2 s at 100k keyframes. With ``--index hnsw`` (the index
``index: auto`` switches to at 100k codes) it also times building that index from the stored codes against taking
back the copy a detector saves beside the store on close (``keyframes.h5.index``).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from retrieval.database import KeyframeDatabase, KeyframeRecord
from retrieval.index import KeyframeIndex
from verify.features import Features

__all__ = ["build_store", "time_open", "main"]

log = logging.getLogger(__name__)


def build_store(path: Path, keyframes: int, features: int = 50, dim: int = 256, seed: int = 0) -> float:
    """Appends ``keyframes`` records to a new store at ``path``; returns the seconds it took."""
    rng = np.random.default_rng(seed)
    kp = rng.uniform(0, 1000, (features, 2)).astype(np.float32)
    feats = Features(kp, rng.integers(0, 256, (features, 128)).astype(np.float32),
                     rng.uniform(2, 30, features).astype(np.float32))
    pose = np.eye(4)[:3]
    t0 = time.perf_counter()
    with KeyframeDatabase(path, {}, "bench", flush_every=1000) as db:
        for i in range(keyframes):
            code = rng.standard_normal(dim).astype(np.float32)
            db.append(KeyframeRecord(i, code / np.linalg.norm(code), feats, float(i) / 10, pose, f"{i:06d}.png",
                                     0.1, np.array([[max(0, i - 60), 0.9, 10, 5, 0.5, 1.0]]), -1))
            if i and i % 10_000 == 0:
                log.info("%d keyframes written (%.0f s)", i, time.perf_counter() - t0)
    return time.perf_counter() - t0


def time_open(path: Path) -> dict[str, float]:
    """Seconds to open the store, and to read every code and every candidate row (checksums verified)."""
    t0 = time.perf_counter()
    db = KeyframeDatabase(path, {}, "bench")
    t_open = time.perf_counter() - t0
    try:
        t0 = time.perf_counter()
        entries = sum(1 for _ in db.search_entries(features=False))
        results = sum(1 for _ in db.results())
        t_read = time.perf_counter() - t0
    finally:
        db.close()
    return {"open_s": t_open, "read_codes_and_results_s": t_read, "keyframes": float(min(entries, results))}


def time_index(path: Path, index: str) -> dict[str, float]:
    """Seconds to build the ``index`` (registry name, defaults) from the store's codes, to save it beside the store,
    and to take the saved copy back as a resume does; the saved file's size."""
    with KeyframeDatabase(path, {}, "bench", mode="r") as db:
        codes, ids = db.codes()
        saved = db.index_path  # where a detector saves its index beside this store
    t0 = time.perf_counter()
    built = KeyframeIndex(codes.shape[1], {"name": index})
    for fid, code in zip(ids.tolist(), codes):
        built.add(fid, code)
    built.admit(int(ids[-1]) + 1)
    t_build = time.perf_counter() - t0
    t0 = time.perf_counter()
    built.save(saved)
    t_save = time.perf_counter() - t0
    t0 = time.perf_counter()
    back = KeyframeIndex(codes.shape[1], {"name": index})
    n = back.restore(saved, ids)
    t_restore = time.perf_counter() - t0
    if n != len(ids):
        raise RuntimeError(f"restored {n} of {len(ids)} keyframes")
    return {"index_build_s": t_build, "index_save_s": t_save, "index_restore_s": t_restore,
            "index_bytes": float(saved.stat().st_size)}


def main(keyframes: int = 100_000, out: str | Path = "runs/bench/store_open", features: int = 50,
         index: str = "") -> dict[str, Any]:
    """Builds the store (rewritten) and times reopening it (and building / restoring ``index`` when given)."""
    out = Path(out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    path = out / "keyframes.h5"
    write_s = build_store(path, keyframes, features)
    res = {"keyframes": keyframes, "write_s": write_s, "bytes": path.stat().st_size, **time_open(path)}
    if index:
        res.update(time_index(path, index))
    return res


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(prog="python -m bench.store_open", description=__doc__.split("\n\n")[0])
    ap.add_argument("--keyframes", type=int, default=100_000)
    ap.add_argument("--features", type=int, default=50, help="local features per keyframe")
    ap.add_argument("--out", default="runs/bench/store_open")
    ap.add_argument("--index", default="", help="also time building this index (e.g. hnsw) against restoring it")
    a = ap.parse_args()
    r = main(a.keyframes, a.out, a.features, a.index)
    print(f"{r['keyframes']} keyframes written in {r['write_s']:.1f} s ({r['bytes'] / 2**20:.0f} MiB); reopened in "
          f"{r['open_s']:.2f} s; codes and candidates read back (checksums verified) in "
          f"{r['read_codes_and_results_s']:.2f} s")
    if a.index:
        print(f"{a.index} index: built from the stored codes in {r['index_build_s']:.1f} s, saved in "
              f"{r['index_save_s']:.2f} s ({r['index_bytes'] / 2**20:.0f} MiB), restored in {r['index_restore_s']:.2f} s")
