"""Memory of the fleet server as one robot streams keyframes: resident memory (RSS) after 100, 200, 500, 1000 and
2000 keyframes, through ``FleetService`` with place recognition in this process (what the server runs behind HTTP).
The robot drives the 200 real KITTI 00 frames of ``../shared`` lap after lap (ground-truth poses, times going on), so
from the second lap on every keyframe revisits a place: loops, verification and graph edges as on a patrol route.

``python -m bench.fleet_memory [--keyframes 2000] [--features database|memory] [--bare] [--out DIR]`` prints a
Markdown table and writes ``fleet_memory.json``. ``--features``: the detectors' ``runtime.features``: read back from
each robot's keyframe database through a bounded cache (the fleet's default), or all kept in memory. ``--bare``: the
same frames through one ``LoopDetector`` with the fleet's detector conf, no fleet (what of the growth is the
detector's). The bar (issue 19): RSS after 2000 within 1.2x of RSS after 200.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import time
from pathlib import Path
from typing import Any, Callable, Sequence

from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from cae_lcd.core.images import read_image
from cae_lcd.core.threads import reexec_with_server_malloc
from cae_lcd.fleet.demo import kitti_stream
from cae_lcd.fleet.recognition import FleetRecognizer
from cae_lcd.fleet.service import FleetService
from cae_lcd.fleet.store import SQLiteStore
from retrieval.detector import LoopDetector

from .common import REPO, md_table

__all__ = ["stream_memory", "main", "MEMORY_FORMAT_VERSION"]

log = logging.getLogger(__name__)

MEMORY_FORMAT_VERSION = 1  #: format of ``fleet_memory.json``
CHECKPOINTS = (50, 100, 200, 300, 400, 500, 1000, 2000, 4000)  #: keyframe counts at which RSS is read


def _rss_mb() -> float:
    """This process's resident memory (Linux ``VmRSS``), MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("VmRSS unknown (not Linux)")


def _target(state: Path, recognition: dict[str, Any] | None, bare: bool,
            K: Any) -> tuple[Callable[..., Any], Callable[[], Any], Callable[[], Any]]:
    """Where the keyframes go: ``(submit(i, t, pose, image), settle(), close())`` of a ``FleetService`` with place
    recognition in process, or (``bare``) of one ``LoopDetector`` with the fleet's detector conf and a database."""
    if bare:
        state.mkdir(parents=True, exist_ok=True)
        det = LoopDetector(FleetRecognizer.resolve(recognition)["detector"], K=K, database=state / "keyframes.h5")

        def process(i: int, t: float, pose: Any, image: Any) -> None:
            det.process(image, i, t, pose)
        return process, lambda: None, det.close
    service = FleetService(SQLiteStore(state / "fleet.sqlite"), None, FleetRecognizer(state, recognition))
    service.register("A")

    def submit(i: int, t: float, pose: Any, image: Any) -> None:
        service.submit_keyframe("A", i, t, pose, image, K)
    return submit, lambda: service.optimize(wait=True, timeout=300), service.close


def stream_memory(kitti_root: str | Path, state: str | Path, keyframes: int = 2000,
                  recognition: dict[str, Any] | None = None, bare: bool = False) -> dict[str, Any]:
    """Streams ``keyframes`` keyframes of KITTI 00 (its 200 frames, lap after lap) as one robot; RSS at each
    checkpoint. ``bare``: through one ``LoopDetector`` with the fleet's detector conf and a keyframe database, no
    fleet (what of the growth is the detector's).

    Returns:
        ``{"keyframes", "rss_mb": {count: MiB}, "seconds": {count: s}, "ratio_2000_200"}``.
    """
    lap = kitti_stream("A", kitti_root, "00", list(range(200)))
    period = float(lap.times[-1] - lap.times[0]) + 1.0
    submit, settle, close = _target(Path(state), recognition, bare, lap.K)
    rss: dict[int, float] = {}
    seconds: dict[int, float] = {}
    started = time.perf_counter()
    try:
        for i in range(keyframes):
            j = i % len(lap.frames)
            submit(i, float(lap.times[j]) + period * (i // len(lap.frames)), lap.poses[j], read_image(lap.images[j]))
            if i + 1 in CHECKPOINTS:
                settle()
                rss[i + 1], seconds[i + 1] = _rss_mb(), time.perf_counter() - started
                log.info("%d keyframes: RSS %.0f MiB, %.0f s", i + 1, rss[i + 1], seconds[i + 1])
    finally:
        close()
    ratio = rss[2000] / rss[200] if 2000 in rss and 200 in rss else None
    return {"format_version": MEMORY_FORMAT_VERSION, "keyframes": keyframes, "rss_mb": rss, "seconds": seconds,
            "ratio_2000_200": ratio}


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitti", type=Path, default=REPO.parent / "shared" / "datasets" / "kitti")
    ap.add_argument("--keyframes", type=int, default=2000, help="keyframes the robot sends")
    ap.add_argument("--features", choices=("database", "memory"), default="database",
                    help="the detectors' runtime.features (the fleet's default: database)")
    ap.add_argument("--bare", action="store_true", help="one LoopDetector with the fleet's detector conf, no fleet")
    ap.add_argument("--server-malloc", action=argparse.BooleanOptionalAction, default=True,
                    help="glibc's malloc as `cae-lcd serve` sets it: arenas capped, mmap threshold fixed (cae_lcd.core.threads)")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench" / "fleet_memory")
    args = ap.parse_args(argv)
    if args.server_malloc:
        reexec_with_server_malloc()
    if not 1 <= args.keyframes <= 4000:
        ap.error("--keyframes must be in 1..4000")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = prepare_out_dir(args.out)
    shutil.rmtree(out / "state", ignore_errors=True)
    r = stream_memory(args.kitti, out / "state", args.keyframes,
                      {"detector": {"runtime": {"features": args.features}}}, args.bare)
    r["features"], r["bare"], r["server_malloc"] = args.features, args.bare, args.server_malloc
    write_text_atomic(out / "fleet_memory.json", json.dumps(r, indent=2))
    print(md_table(["keyframes", "RSS MiB", "elapsed s"],
                   [[n, f"{r['rss_mb'][n]:.0f}", f"{r['seconds'][n]:.0f}"] for n in r["rss_mb"]]))


if __name__ == "__main__":
    main()
