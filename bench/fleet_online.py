"""The fleet's robots calibrating online (issue 27): real KITTI frames streamed as robots through one
``FleetRecognizer`` (what the server runs behind HTTP), robot after robot or interleaved; the intra-robot loop
edges (delayed ones among them) and the cross-robot overlaps the calibrated test accepted, each scored against the ground truth, the ms per
keyframe and the worst request (a refit runs on the request that triggers it).

``python -m bench.fleet_online [--set 90split|90one|00-07] [--exclude-recent 50] [--fixed] [--interleave]``
prints one JSON summary (and writes it to ``--out``):

- ``90split``: KITTI 90 as two robots, A frames 0-99 (the first pass), B frames 100-199 (the second pass, which
  revisits A's road): every cross-robot edge is scored by ``sequences/90/loops.txt`` (pairs in the 200-frame
  indexing; keyframe ids are the frame indices);
- ``90one``: KITTI 90 as one robot (its loops scored the same way; the worst request is its refit);
- ``00-07``: KITTI 00 as robot A (200 frames), 07 as robot B (160): they never meet, every accepted overlap is
  false;
- ``00laps``: KITTI 00 as one robot driving its 200 frames lap after lap, ``--keyframes`` in all (keyframe ids
  0, 1, ...; from the second lap on every keyframe revisits a place): what a refit at a large map costs.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cae_lcd.core.files import write_text_atomic
from cae_lcd.fleet.demo import RobotStream, kitti_stream
from cae_lcd.fleet.recognition import FleetRecognizer, certified_match
from retrieval.descriptors import create_descriptor

from .common import REPO

__all__ = ["SETS", "stream_robots", "main"]

KITTI = REPO.parent / "shared" / "datasets" / "kitti"  #: the shared KITTI folder (``sequences/``, ``poses/``)
SETS = {  #: robot name -> (sequence, frames), per set
    "90split": {"A": ("90", range(0, 100)), "B": ("90", range(100, 200))},
    "90one": {"A": ("90", range(0, 200))},
    "00-07": {"A": ("00", range(0, 200)), "B": ("07", range(0, 160))},
    "00laps": {"A": ("00", range(0, 200))},  # lap after lap (``--keyframes``)
}


def _truth(kitti_root: Path) -> set[frozenset[int]]:
    """KITTI 90's true pairs (``loops.txt``: ``query match`` in the 200-frame indexing), unordered."""
    rows = np.loadtxt(kitti_root / "sequences" / "90" / "loops.txt", dtype=np.int64).reshape(-1, 2)
    return {frozenset(map(int, r)) for r in rows}


def _laps(stream: RobotStream, n: int) -> RobotStream:
    """``stream`` driven again and again: ``n`` keyframes, ids ``0..n-1``, 0.1 s apart, the same poses each lap."""
    lap = np.arange(n) % len(stream.frames)
    return RobotStream(stream.name, list(range(n)), [stream.images[i] for i in lap], stream.poses[lap],
                       np.arange(n) * 0.1, stream.K)


def stream_robots(state: Path, robots: dict[str, tuple[str, range]], conf: dict[str, Any] | None,
                  descriptor: Any, kitti_root: Path = KITTI, interleave: bool = False,
                  keyframes: int | None = None) -> dict[str, Any]:
    """Streams each robot's frames (robot after robot, or ``interleave``d one keyframe each in turn) through one
    recognizer (``keyframes``: each robot's frames lap after lap, this many: ``_laps``); returns its edges, overlaps recorded (an accepted pair's first edge records it), the pairs the rule
    accepted (with or without an edge), per-request ms and each robot's ``certified_match`` at the end."""
    streams = {name: kitti_stream(name, kitti_root, seq, list(frames)) for name, (seq, frames) in robots.items()}
    if keyframes is not None:
        streams = {name: _laps(s, keyframes) for name, s in streams.items()}
    order = [(n, i) for i in range(max(len(s.frames) for s in streams.values())) for n in streams
             if i < len(streams[n].frames)] if interleave else \
        [(n, i) for n, s in streams.items() for i in range(len(s.frames))]
    rec = FleetRecognizer(state, conf, descriptor)
    edges, overlaps, ms, delayed = [], [], [], 0
    for name, i in order:
        s = streams[name]
        image = cv2.imread(str(s.images[i]), cv2.IMREAD_UNCHANGED)
        t0 = time.perf_counter()
        found = rec.process(name, s.frames[i], float(s.times[i]), s.poses[i], image, s.K)
        ms.append((time.perf_counter() - t0) * 1e3)
        edges += found.edges
        delayed += sum(e.kind == "loop" and e.keyframe_b != s.frames[i] for e in found.edges)  # an earlier query's
        overlaps += found.overlaps
    accepted = sorted({tuple(sorted(pair)) for pair, rule in rec.tracker.rules.items() if rule.accepted is not None})
    window = rec.detector_conf["search"]["exclude_recent"]
    certified = {n: certified_match(rec.robots[n].detector.deciding_calibration, window) for n in streams}
    rec.close()
    return {"edges": edges, "overlaps": overlaps, "ms": np.array(ms), "order": order, "certified": certified,
            "delayed": delayed, "accepted": accepted}


def _score(run: dict[str, Any], truth: set[frozenset[int]] | None, robots: dict[str, tuple[str, range]]
           ) -> dict[str, Any]:
    """Counts (and, with ``truth``, the precision of) the loop and overlap edges; the request times."""
    out: dict[str, Any] = {"certified_inliers_run": run["certified"], "delayed_loop_edges": run["delayed"],
                           "overlaps_accepted": [(o.robot_a, o.robot_b) for o in run["overlaps"]],
                           "pairs_the_rule_accepted": run["accepted"]}
    for kind in ("loop", "overlap"):
        got = [e for e in run["edges"] if e.kind == kind]
        out[f"{kind}_edges"] = len(got)
        if truth is not None and all(seq == "90" for seq, _ in robots.values()):
            right = sum(frozenset((e.keyframe_a, e.keyframe_b)) in truth for e in got)
            out[f"{kind}_precision"] = right / len(got) if got else None
        elif truth is None:
            out[f"{kind}_false"] = len(got) if kind == "overlap" else None
    ms = run["ms"]
    worst = int(np.argmax(ms)) if len(ms) else -1
    out.update({"keyframes": len(ms), "ms_per_keyframe_mean": float(ms.mean()) if len(ms) else None,
                "ms_per_keyframe_median": float(np.median(ms)) if len(ms) else None,
                "worst_request_ms": float(ms[worst]) if len(ms) else None,
                "worst_request": list(run["order"][worst]) if len(ms) else None})
    return out


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Runs one set (see the module doc) and prints its summary as JSON."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=sorted(SETS), default="90split", help="which robots (module doc)")
    ap.add_argument("--exclude-recent", type=int, default=None,
                    help="detector.search.exclude_recent (default: the detector's; the warm-up is twice it)")
    ap.add_argument("--fixed", action="store_true", help="the fixed policy (detector.calibration.enabled: false)")
    ap.add_argument("--interleave", action="store_true", help="robots send one keyframe each in turn")
    ap.add_argument("--keyframes", type=int, default=2000, help="00laps: keyframes in all")
    ap.add_argument("--out", default=None, help="also write the summary (JSON) here")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    detector: dict[str, Any] = {}
    if args.exclude_recent is not None:
        detector["search"] = {"exclude_recent": args.exclude_recent}
    if args.fixed:
        detector["calibration"] = {"enabled": False}
    robots = SETS[args.set]
    with tempfile.TemporaryDirectory() as state:
        run = stream_robots(Path(state), robots, {"detector": detector}, create_descriptor({"name": "cae"}),
                            interleave=args.interleave, keyframes=args.keyframes if args.set == "00laps" else None)
    summary = {"set": args.set, "detector": detector, "interleave": args.interleave, "slowest_requests": [
                   (list(run["order"][i]), float(run["ms"][i])) for i in np.argsort(run["ms"])[::-1][:8]],
               **_score(run, _truth(KITTI) if args.set.startswith("90") else None, robots)}
    text = json.dumps(summary, indent=2, default=str)
    print(text)  # noqa: T201 -- a bench's report
    if args.out:
        write_text_atomic(Path(args.out), text)
    return summary


if __name__ == "__main__":
    main()
