"""How the default geometric threshold was chosen: the inlier counts of true and false candidates on real data.

Runs detection with ``policy.min_inliers: 0`` (every candidate with enough matches gets the full geometric check)
on KITTI 90 (revisits), 00 and 07 (no revisit), then reports for each sequence the strongest false candidate that
would be accepted as a query's best (its inliers) and the weakest true loop, and the false/true loops at several
thresholds. ``python -m bench.choose_policy [--shared ../shared] [--out runs/policy] [--config FILE]``.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from cae_lcd.core.conf import load_conf_file
from cae_lcd.evaluation.metrics import best_per_query, correct_mask
from retrieval.run_folder import CANDIDATE_COLUMNS, RunFolder, read_csv_table

from .common import detect_run, ground_truth_pairs

THRESHOLDS = (20, 30, 40, 50, 60, 80)


def study(shared: Path, out: Path, conf: dict | None = None,
          sequences: tuple[str, ...] = ("90", "00", "07")) -> list[dict]:
    """Runs the three sequences with ``conf`` (policy.min_inliers forced to 0) and tabulates inlier counts."""
    rows = []
    for name in sequences:
        root = shared / "datasets/kitti/sequences" / name
        run = out / name
        detect_run(root, run, {**(conf or {}), "policy": {"min_inliers": 0, "check_all": True}})  # a fresh run
        gt = ground_truth_pairs(root)
        gt = np.zeros((0, 2), np.int64) if gt is None else gt
        cands = read_csv_table(RunFolder(run).candidates, CANDIDATE_COLUMNS)
        det, inliers = best_per_query(cands, "inliers", min_matches=5)
        ok = correct_mask(det, gt)
        row = {"sequence": name, "strongest_false": int(inliers[~ok].max()) if (~ok).any() else 0,
               "weakest_true": int(inliers[ok].min()) if ok.any() else None}
        for t in THRESHOLDS:
            row[t] = (int((ok & (inliers >= t)).sum()), int((~ok & (inliers >= t)).sum()))
        rows.append(row)
    return rows


if __name__ == "__main__":
    logging.basicConfig(level=logging.WARNING)
    ap = argparse.ArgumentParser(prog="python -m bench.choose_policy", description=__doc__.split("\n\n")[0])
    ap.add_argument("--shared", type=Path, default=Path("../shared"))
    ap.add_argument("--out", type=Path, default=Path("runs/policy"))
    ap.add_argument("--config", type=Path, help="detector config to study (default: the built-in defaults)")
    args = ap.parse_args()
    rows = study(args.shared, args.out, load_conf_file(args.config) if args.config else None)
    print("| sequence | strongest false best-candidate (inliers) | weakest true loop (inliers) | "
          + " | ".join(f"true/false at >= {t}" for t in THRESHOLDS) + " |")
    print("|---" * (3 + len(THRESHOLDS)) + "|")
    for r in rows:
        weakest = "-" if r["weakest_true"] is None else r["weakest_true"]
        print(f"| {r['sequence']} | {r['strongest_false']} | {weakest} | "
              + " | ".join(f"{r[t][0]}/{r[t][1]}" for t in THRESHOLDS) + " |")
