"""Cost against map size: streams ``--frames`` real frames (KITTI from ``../shared``, augmented past the first
pass) through one ``LoopDetector`` with a keyframe store, and reports ms a frame and memory as the map grows:
``python -m bench.stream --frames 100000``.

Writes ``runs/bench/stream/stream.json`` (one point per window: map size, median and p90 ms a frame, RSS), a plot
``stream.png`` and a Markdown table ``stream.md``. The target: ms a frame at 100k keyframes within 1.5x of that at
1k. The streamed detector has no sequence to calibrate on, so it whitens its codes with a whitening fitted on its
own first 1024 keyframes (``whitening.stream_fit``), and its store keeps a small grey copy of each keyframe instead
of its local features (``runtime.features: image``), which are extracted only for frames with a candidate that
could pass, and for those candidates: what grows with the map is the index and the in-memory columns.
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from cae_lcd.core.conf import merge_conf
from retrieval.detector import LoopDetector

from .augment import augmented_frames, shared_frames
from .common import md_table

__all__ = ["stream", "stream_table", "main"]

log = logging.getLogger(__name__)

#: the streamed detector: fixed policy (a stream has no sequence to calibrate on), whitened on its own first
#: keyframes, a grey copy per keyframe in the store instead of its features
STREAM_CONF: dict[str, Any] = {"calibration": {"enabled": False}, "whitening": {"stream_fit": 1024},
                               "runtime": {"features": "image"}}


def _rss_mb() -> float:
    """Resident memory now (MB), from /proc; the peak where /proc is not there."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * resource.getpagesize() / 2**20
    except (OSError, IndexError, ValueError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def stream(frames: int, out: str | Path = "runs/bench/stream", window: int = 0, seed: int = 0,
           conf: dict[str, Any] | None = None) -> dict[str, Any]:
    """Streams ``frames`` augmented real frames through a detector writing ``out/keyframes.h5``.

    Args:
        frames: frames streamed.
        out: working folder (rewritten).
        window: frames per reported point (0: ``frames / 20``, at least 50).
        seed: seeds the augmentations.
        conf: detector conf merged over ``STREAM_CONF``.

    Returns:
        ``{"points": [{"frames", "keyframes", "ms_median", "ms_p90", "rss_mb", "cpu_ms"}], "frames", "peak_rss_mb",
        "store_bytes_per_frame", "wall_s"}``.
    """
    out = Path(out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    window = window or max(50, frames // 20)
    paths = shared_frames(kitti_only=True)
    det = LoopDetector(merge_conf(STREAM_CONF, conf or {}, strict=False), database=out / "keyframes.h5")
    points, ms = [], []
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    try:
        for i, (path, image) in enumerate(augmented_frames(paths, frames, seed)):
            ms.append(det.process(image, source=path.name).ms["total"])
            if len(ms) == window or i == frames - 1:
                cpu = time.process_time()
                points.append({"frames": i + 1, "keyframes": len(det.places), "ms_median": float(np.median(ms)),
                               "ms_p90": float(np.percentile(ms, 90)), "rss_mb": _rss_mb(),
                               "cpu_ms": 1000 * (cpu - cpu0) / len(ms)})
                cpu0 = cpu
                log.info("%d frames, %d keyframes: %.1f ms a frame (median), %.1f ms of CPU a frame (mean, with the "
                         "augmentation), RSS %.0f MB", i + 1, points[-1]["keyframes"], points[-1]["ms_median"],
                         points[-1]["cpu_ms"], points[-1]["rss_mb"])
                ms = []
    finally:
        det.close()
    size = sum(p.stat().st_size for p in out.iterdir() if p.is_file())
    return {"points": points, "frames": frames, "wall_s": time.perf_counter() - t0,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "store_bytes_per_frame": size / max(1, frames), "image_size": list(image.shape[:2])}


def stream_table(res: dict[str, Any]) -> str:
    """Markdown: one row per reported point, and the ratio of the last point's median to the first's."""
    pts = res["points"]
    rows = [[p["frames"], p["keyframes"], f"{p['ms_median']:.1f}", f"{p['ms_p90']:.1f}",
             f"{p.get('cpu_ms', float('nan')):.1f}", f"{p['rss_mb']:.0f}"] for p in pts]
    ratio = pts[-1]["ms_median"] / max(pts[0]["ms_median"], 1e-9) if pts else float("nan")
    return (md_table(["frames", "keyframes", "ms/frame (median)", "ms/frame (p90)",
                      "CPU ms/frame (mean, with augmentation)", "RSS MB"], rows)
            + f"\n\n- {res['frames']} frames ({res['image_size'][1]}x{res['image_size'][0]}), {res['wall_s']:.0f} s; "
            f"last / first window median: {ratio:.2f}x (target <= 1.5x); peak RSS {res['peak_rss_mb']:.0f} MB; "
            f"store {res['store_bytes_per_frame'] / 1024:.1f} KB a frame.")


def _plot(res: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = res["points"]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot([p["keyframes"] for p in pts], [p["ms_median"] for p in pts], "o-", label="ms/frame (median)")
    ax.set_xlabel("keyframes in the map")
    ax.set_ylabel("ms a frame")
    ax2 = ax.twinx()
    ax2.plot([p["keyframes"] for p in pts], [p["rss_mb"] for p in pts], "s--", color="tab:red", label="RSS MB")
    ax2.set_ylabel("RSS (MB)")
    fig.legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(frames: int = 10_000, out: str | Path = "runs/bench/stream", window: int = 0, seed: int = 0
         ) -> dict[str, Any]:
    """Runs ``stream`` and writes ``stream.json``, ``stream.png`` and ``stream.md`` into ``out``."""
    res = stream(frames, out, window, seed)
    out = Path(out)
    (out / "stream.json").write_text(json.dumps(res, indent=1))
    (out / "stream.md").write_text("### Cost against map size (stream)\n\n" + stream_table(res) + "\n")
    _plot(res, out / "stream.png")
    return res


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(prog="python -m bench.stream", description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=10_000)
    ap.add_argument("--out", default="runs/bench/stream")
    ap.add_argument("--window", type=int, default=0, help="frames per reported point (0: frames / 20)")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    print(stream_table(main(a.frames, a.out, a.window, a.seed)))
