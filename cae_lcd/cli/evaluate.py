"""``cae-lcd evaluate RUN --gt GROUND_TRUTH``: ``cae_lcd.evaluation.evaluate.main`` from the command line."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cae_lcd.core.cli import api_defaults
from cae_lcd.evaluation import evaluate
from cae_lcd.evaluation.ground_truth import WORLDS
from cae_lcd.evaluation.metrics import SCORES

__all__ = ["add_parser", "run", "add_world_argument"]

_DEFAULTS = api_defaults(evaluate.main)


def add_parser(sub: Any) -> None:
    p = sub.add_parser("evaluate", help="evaluate a detect run against ground truth (PR, AUC, Recall@k, plots)",
                       description=evaluate.__doc__.split("\n\n")[0])
    p.add_argument("run", help="run folder written by 'cae-lcd detect', or a loops.csv")
    p.add_argument("--gt", default=_DEFAULTS["gt"], help="ground truth: 'i j' pairs file (0-based) or KITTI poses "
                   "file (default: the one detect found: the sequence's loops.txt or, for TUM / EuRoC, loops derived "
                   "from its poses)")
    p.add_argument("--out", help="folder for evaluation.json and the PNGs (default: the run folder)")
    p.add_argument("--radius", type=float, default=_DEFAULTS["radius"],
                   help="poses ground truth: loop radius on the x-z plane, metres (default %(default)s)")
    p.add_argument("--min-gap", type=int, default=_DEFAULTS["min_gap"],
                   help="poses ground truth: minimum frame gap (default %(default)s)")
    p.add_argument("--min-gap-s", type=float, default=_DEFAULTS["min_gap_s"],
                   help="poses ground truth: minimum time gap in seconds, replaces --min-gap (needs times)")
    p.add_argument("--times", help="times.txt for --min-gap-s (default: the run's sequence's times.txt)")
    p.add_argument("--score", choices=SCORES, default=_DEFAULTS["score"],
                   help="score swept for the PR curve (default %(default)s)")
    add_world_argument(p, _DEFAULTS["world"])
    p.set_defaults(func=run)


def add_world_argument(p: Any, default: str) -> None:
    """``--world``: the ground-truth poses' world convention (``cae_lcd.evaluation.ground_truth.WORLDS``)."""
    p.add_argument("--world", choices=list(WORLDS), default=default,
                   help="ground-truth poses' world: z-up (TUM, EuRoC), y-down (KITTI, evo from KITTI poses) or auto "
                        "(the gravity axis found from the trajectory; default %(default)s)")


def run(args: Any) -> None:
    evaluate.main(Path(args.run), None if args.gt is None else Path(args.gt),
                  None if args.out is None else Path(args.out), args.radius, args.min_gap, args.min_gap_s, args.score,
                  None if args.times is None else Path(args.times), args.world)
