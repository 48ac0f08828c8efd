"""``cae-lcd fleet-demo --out DIR``: ``cae_lcd.fleet.demo.run_demo`` (a server and two robots streaming KITTI on loopback),
then the recovered transform's errors against the known truth."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from cae_lcd.core.cli import add_missing_extra, api_defaults

__all__ = ["add_parser", "run", "DEFAULT_KITTI"]

log = logging.getLogger("cae_lcd.fleet_demo")

DEFAULT_KITTI = Path(__file__).resolve().parents[2].parent / "shared" / "datasets" / "kitti"  #: ../shared KITTI


def add_parser(sub: Any) -> None:
    try:  # here, not at the top: the detector installs without the fleet's dependencies
        from cae_lcd.fleet.demo import run_demo
    except ImportError as err:
        add_missing_extra(sub, "fleet-demo", "fleet", err)
        return
    defaults = api_defaults(run_demo)
    p = sub.add_parser("fleet-demo", help="fleet server demo: two robots stream KITTI 00, the server merges them",
                       description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="output folder (fleet_demo.json, trajectories.png, trajectories/, state/)")
    p.add_argument("--kitti", default=str(DEFAULT_KITTI), help=f"KITTI folder (default: {DEFAULT_KITTI})")
    p.add_argument("--frames", type=int, default=defaults["frames"],
                   help=f"first frames of 00 streamed (default: {defaults['frames']})")
    p.add_argument("--negative", action="store_true", default=defaults["negative"],
                   help="robots on 00 and 07, which never meet: any overlap is a false one")
    p.add_argument("--hostile", action="store_true", default=defaults["hostile"],
                   help="then again with a third robot streaming garbage: how far it moves the two good maps")
    p.set_defaults(func=run)


def run(args: Any) -> None:
    from cae_lcd.fleet.demo import run_demo

    logging.getLogger("httpx").setLevel(logging.WARNING)  # one line a request otherwise
    s = run_demo(args.out, args.kitti, negative=args.negative, frames=args.frames, hostile=args.hostile)
    log.info("%s demo: %d + %d keyframes in %.1f s (%.2f keyframes/s); overlaps %d, overlap edges %d", s["mode"],
             s["keyframes"]["A"], s["keyframes"]["B"], s["wall_s"], s["keyframes_per_s"], len(s["overlaps"]),
             s["overlap_edges"])
    if s["mode"] == "negative":
        log.info("false overlaps between robots that never meet: %d", s["false_overlaps"])
    elif "rotation_error_deg" in s:
        log.info("transform of B: rotation error %.3f deg, scale error %.3f %%, translation error %.3f %% of "
                 "%.1f m (%.3f m); merged B trajectory RMSE %.3f m", s["rotation_error_deg"], s["scale_error_pct"],
                 s["translation_error_pct"], s["trajectory_length_m"], s["translation_error_m"],
                 s["merged_b_rmse_m"])
    else:
        log.warning("the server did not merge robot B")
    if "hostile" in s:
        h = s["hostile"]
        log.info("hostile robot H (%d keyframes, %s refused, merged: %s): moves A by %.3f m, B by %.3f m (against "
                 "the run without H: %.3f m, %.3f m); errors with H: %s", h["keyframes"], h["refused"].get("H", 0),
                 h["merged_H"], h["moved_m"]["A"], h["moved_m"]["B"], h["run_to_run_m"]["A"], h["run_to_run_m"]["B"],
                 h["errors_with_H"])
    log.info("wrote %s/{fleet_demo.json,trajectories.png,trajectories/*.tum,*.kitti}", args.out)
