"""Speed and memory of one detector: ms/frame by stage at full resolution, peak memory, bytes per keyframe, and the
encoder's throughput (batch 1 vs batched, channels-last vs contiguous memory)."""

from __future__ import annotations

import copy
import logging
import os
import platform
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from cae.preprocess import preprocess
from retrieval.detector import STAGES

from .common import detect_run, md_table

__all__ = ["STAGE_NAMES", "system_info", "stage_benchmark", "stage_table", "encoder_throughput", "throughput_table"]

log = logging.getLogger(__name__)

#: table label of each stage; which stages there are, and their order, is ``retrieval.detector.STAGES``
STAGE_NAMES = {"gate": "gate (Canny edge ratio)", "encode": "encode (preprocess + CAE + whitening)",
               "features": "SIFT features", "search": "search (faiss)", "filter": "temporal filter (hypotheses)",
               "verify": "match + verify (ratio test, RANSAC)", "insert": "insert (index + HDF5)",
               "total": "end to end"}


def system_info() -> dict[str, Any]:
    """CPU model, core count, load average, library versions: what the timings depend on."""
    import faiss

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "load_avg": os.getloadavg() if hasattr(os, "getloadavg") else None,
            "torch": torch.__version__, "faiss": faiss.__version__, "python": platform.python_version()}


def stage_benchmark(sequence: str | Path, out: str | Path, conf: dict[str, Any] | None = None) -> dict[str, Any]:
    """One detect run in a fresh process: its summary, peak RSS and bytes stored per keyframe."""
    summary = detect_run(sequence, out, conf, isolate=True)
    h5 = Path(out) / "keyframes.h5"
    summary["bytes_per_keyframe"] = h5.stat().st_size / max(1, summary["keyframes"])
    return summary


def stage_table(summary: dict[str, Any], image_size: str) -> str:
    """Markdown: ms/frame (median, p90) by stage, then memory and storage lines."""
    ms = summary["ms_per_frame"]
    rows = [[STAGE_NAMES.get(s, s), f"{ms[s]['median']:.1f}", f"{ms[s]['p90']:.1f}"] for s in STAGES if s in ms]
    table = md_table(["stage", "median ms", "p90 ms"], rows)
    rss = summary.get("peak_rss_bytes")
    notes = [
        f"- {summary['frames']} frames ({image_size}), {summary['keyframes']} keyframes, {summary['wall_s']:.0f} s "
        f"wall for the run, default runtime (stages one after another on all cores; the end-to-end time also holds "
        f"the conversions between stages, and each column's median is taken on its own).",
        f"- Peak memory (max RSS of the detect process, Python + torch + faiss included): "
        f"{'n/a' if rss is None else f'{rss / 2**20:.0f} MiB'}.",
        f"- Stored per keyframe (keyframes.h5 size / keyframes: code + SIFT keypoints and descriptors): "
        f"{summary['bytes_per_keyframe'] / 1024:.1f} KiB.",
    ]
    return table + "\n\n" + "\n".join(notes)


def _time_passes(fn: Any, min_time_s: float, min_passes: int = 3) -> float:
    """Median seconds of one ``fn()`` call after a warm-up, over at least ``min_passes`` / ``min_time_s``."""
    fn()
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < min_passes or time.perf_counter() - start < min_time_s:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


@torch.inference_mode()
def encoder_throughput(encoder: torch.nn.Module, images: Sequence[np.ndarray], batch_sizes: Sequence[int] = (1, 32),
                       min_time_s: float = 2.0) -> dict[str, Any]:
    """Images per second of the encoder network, by batch size and memory format (same inputs, same run).

    Args:
        encoder: a loaded ``cae.Encoder`` (any memory format; copies are made for each format).
        images: real frames (as read); the batches cycle through them.
        batch_sizes: batch sizes to time.
        min_time_s: time each setting for at least this long (median of passes).

    Returns:
        ``{"rows": [{"batch", "format", "images_per_s", "ms_per_image"}], "preprocess_ms": float,
        "threads": int, "image_size": str}``.
    """
    threads = os.cpu_count() or 1
    torch.set_num_threads(threads)
    n = max(batch_sizes)
    frames = [images[i % len(images)] for i in range(n)]
    pre_s = _time_passes(lambda: preprocess(frames[:8]), min_time_s / 4)
    x = preprocess(frames)
    models = {fmt: copy.deepcopy(encoder).to(memory_format=mf).eval()
              for fmt, mf in (("channels_last", torch.channels_last), ("contiguous", torch.contiguous_format))}
    rows = []
    for b in batch_sizes:
        for fmt, model in models.items():
            mf = torch.channels_last if fmt == "channels_last" else torch.contiguous_format
            xb = x[:b].contiguous(memory_format=mf)
            s = _time_passes(lambda: model(xb), min_time_s)
            rows.append({"batch": b, "format": fmt, "images_per_s": b / s, "ms_per_image": s * 1e3 / b})
            log.info("encoder batch %d %s: %.1f images/s", b, fmt, b / s)
    h, w = images[0].shape[:2]
    return {"rows": rows, "preprocess_ms": pre_s * 1e3 / 8, "threads": threads, "image_size": f"{w}x{h}"}


def throughput_table(res: dict[str, Any]) -> str:
    """Markdown: images/s by batch and memory format, with the channels-last speed-up."""
    by = {(r["batch"], r["format"]): r for r in res["rows"]}
    rows = []
    for b in sorted({r["batch"] for r in res["rows"]}):
        cl, ct = by[(b, "channels_last")], by[(b, "contiguous")]
        rows.append([str(b), f"{cl['images_per_s']:.1f} ({cl['ms_per_image']:.1f} ms)",
                     f"{ct['images_per_s']:.1f} ({ct['ms_per_image']:.1f} ms)",
                     f"{cl['images_per_s'] / ct['images_per_s']:.2f}x"])
    table = md_table(["batch", "channels_last img/s (ms/img)", "contiguous img/s (ms/img)", "channels_last speed-up"],
                     rows)
    return (table + f"\n\n- Network only, input 3x256x256, torch threads = {res['threads']} (all cores). "
            f"Preprocessing a {res['image_size']} frame (resize to 256x256, grey -> RGB, to float) adds "
            f"{res['preprocess_ms']:.1f} ms/image on top.")
