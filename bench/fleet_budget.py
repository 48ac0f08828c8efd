"""What the verification budget costs (``recognition.cross.budget``): N robots on KITTI 00 (robot ``r`` sends frames
``r, r + N, ...``: every pair overlaps), one ``FleetRecognizer`` in process, once per budget; the candidates verified
per keyframe, the overlap edges and accepted robot pairs, each against no budget (their recall), and the time.

``python -m bench.fleet_budget [--robots 8] [--keyframes 12] [--budgets 0,2,4,8]`` prints a Markdown table and
writes ``fleet_budget.json`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any, Sequence

import cv2

from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from cae_lcd.fleet.demo import kitti_stream
from cae_lcd.fleet import recognition
from cae_lcd.fleet.budget import shortlist
from cae_lcd.fleet.recognition import FIXED_POLICY, FleetRecognizer
from retrieval.descriptors import create_descriptor

from .common import REPO, md_table

__all__ = ["budget_cost", "main"]


def _run(kitti_root: Path, robots: int, keyframes: int, budget: int, descriptor: Any) -> dict[str, Any]:
    """One pass over the interleaved robots with ``cross.budget = budget``."""
    streams = [kitti_stream(f"R{r:02d}", kitti_root, "00", list(range(r, r + robots * keyframes, robots)))
               for r in range(robots)]
    with tempfile.TemporaryDirectory() as state:
        # the fixed policy: 12 keyframes a robot are within a detector's online warm-up (nothing verified there)
        rec = FleetRecognizer(state, {**FIXED_POLICY, "cross": {"budget": budget}}, descriptor)
        verified = [0]
        edges, pairs = 0, set()
        t0 = time.perf_counter()
        recognition.shortlist = _counting(verified)
        for i in range(keyframes):
            for s in streams:
                found = rec.process(s.name, s.frames[i], float(s.times[i]), s.poses[i],
                                    cv2.imread(str(s.images[i]), cv2.IMREAD_UNCHANGED), s.K)
                edges += sum(e.kind == "overlap" for e in found.edges)
                pairs |= {frozenset((o.robot_a, o.robot_b)) for o in found.overlaps}
        wall = time.perf_counter() - t0
        recognition.shortlist = shortlist
        rec.close()
    n = robots * keyframes
    return {"budget": budget, "keyframes": n, "verified_per_keyframe": verified[0] / n, "overlap_edges": edges,
            "accepted_pairs": len(pairs), "s_per_keyframe": wall / n}


def _counting(verified: list[int]) -> Any:
    """``cae_lcd.fleet.budget.shortlist`` that adds the number of candidates it chooses (those verified) to ``verified[0]``."""

    def counted(*args: Any) -> dict[str, Any]:
        chosen = shortlist(*args)
        verified[0] += sum(len(ids) for ids in chosen.values())
        return chosen

    return counted


def budget_cost(kitti_root: Path, robots: int = 8, keyframes: int = 12,
                budgets: Sequence[int] = (0, 2, 4, 8)) -> list[dict[str, Any]]:
    """One ``_run`` per budget; recall of edges and pairs relative to the first (no budget: 0)."""
    descriptor = create_descriptor({"name": "cae"})
    rows = [_run(kitti_root, robots, keyframes, b, descriptor) for b in budgets]
    for r in rows:
        r["edge_recall"] = r["overlap_edges"] / max(1, rows[0]["overlap_edges"])
        r["pair_recall"] = r["accepted_pairs"] / max(1, rows[0]["accepted_pairs"])
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--kitti", type=Path, default=REPO.parent / "shared" / "datasets" / "kitti")
    ap.add_argument("--robots", type=int, default=8)
    ap.add_argument("--keyframes", type=int, default=12, help="keyframes each robot sends")
    ap.add_argument("--budgets", default="0,2,4,8", help="comma-separated budgets; the first is the reference")
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "bench" / "fleet_budget")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    out = prepare_out_dir(args.out)
    rows = budget_cost(args.kitti, args.robots, args.keyframes, [int(b) for b in args.budgets.split(",")])
    write_text_atomic(out / "fleet_budget.json", json.dumps(rows, indent=2))
    print(md_table(["budget", "verified per keyframe", "overlap edges", "edge recall", "accepted pairs",
                    "pair recall", "s per keyframe"],
                   [[r["budget"] or "none", f"{r['verified_per_keyframe']:.1f}", r["overlap_edges"],
                     f"{r['edge_recall']:.0%}", r["accepted_pairs"], f"{r['pair_recall']:.0%}",
                     f"{r['s_per_keyframe']:.2f}"] for r in rows]))


if __name__ == "__main__":
    main()
