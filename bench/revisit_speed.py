"""A revisit at another speed (issue 27): each loop must name the place the query stands at.

KITTI 90's first pass whole and its second pass taking frames 1.15, 1.25, 2 or 3 apart (frame `100 + round(v k)`: the
road driven again 1.15x, 1.25x, 2x or 3x as fast); and a revisit slower than the map (0.5x, 0.333x): the first pass
taking every second or third frame (a sparse map, keyframes 3.1 or 4.7 m apart), then 40 frames of KITTI 07 (the
robot elsewhere: the revisit lies beyond the exclusion window), then the second pass whole. At full size (1241x376),
at 160x120, at 64x32 (too few keypoints to verify: the score path decides, on lines at the map's speed and 15 % either
side by default) and at 160x120 with the second pass made darker (`bench.aliasing.DARKER`: a night revisit whose
frames cannot be verified, the score path decides), as plain folders (no calibration); `cae-lcd detect` with the
default config, with the verified runs fused on lines at the map's speed only (`calibration.speeds: [1.0]`; the
default fuses them at 1x, 2x and 3x, `retrieval.decision`), without the walk that names where the query stands
(`search.localise_steps: 0`, `retrieval.localise`), and with the score path's windows on lines at the map's speed only
(`calibration.score_speeds: [1.0]`, the default before) and at 1x, 2x and 3x (`calibration.score_speeds: [1, 2, 3]`;
the verified paths read neither). A loop is true where the ground truth (5 m on the ground plane) holds its pair; its
distance is read from `poses/90.txt` (a loop to a KITTI 07 frame is false, no distance).

``python -m bench.revisit_speed [--out runs/bench/revisit_speed] [--no-write]``
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from .common import REPO, md_table, work_study_cli

log = logging.getLogger(__name__)

SPEEDS = (1 / 3, 0.5, 1.15, 1.25, 2.0, 3.0)  #: the second pass at ``v`` times the map's speed (``speed_folder``)
SIZES = {  #: name -> (size, whether the second pass is made darker: ``bench.aliasing.DARKER``, too few keypoints)
    "full size": (None, False), "160x120": ((160, 120), False), "64x32 (score path)": ((64, 32), False),
    "160x120, second pass darker (score path: a night)": ((160, 120), True)}
KITTI90 = REPO.parent / "shared" / "datasets" / "kitti" / "sequences" / "90"  #: the sequence and its ground truth
ELSEWHERE = 40  #: KITTI 07 frames between a sparse map and its slower revisit (the robot elsewhere)
VARIANTS = {"default": {},
            "runs at the map's speed only (`calibration.speeds: [1.0]`)": {"calibration": {"speeds": [1.0]}},
            "without the walk (`search.localise_steps: 0`)": {"search": {"localise_steps": 0}},
            "score path at the map's speed only (`calibration.score_speeds: [1.0]`)":
                {"calibration": {"score_speeds": [1.0]}},
            "score path at 1x, 2x, 3x (`calibration.score_speeds: [1, 2, 3]`)":
                {"calibration": {"score_speeds": [1.0, 2.0, 3.0]}}}


def speed_folder(out: Path, speed: float, size: tuple[int, int] | None,
                 darker: bool = False) -> tuple[Path, list[int]]:
    """KITTI 90's two passes with the second at ``speed`` times the first's, resized to ``size``, the second pass
    made darker (``bench.aliasing.DARKER``, seed 0) where asked, as a plain folder under ``out``; and each written
    frame's index in KITTI 90 (-1: a KITTI 07 frame). Faster (``speed >= 1``): the first pass whole (frames 0-99),
    the second taking frames ``100 + round(speed k)``. Slower: the first pass taking frames ``round(k / speed)``, then
    ``ELSEWHERE`` frames of KITTI 07, then the second pass whole (100-199)."""
    from retrieval.sequences import open_sequence

    from .aliasing import DARKER, plain_folder
    from .augment import darken

    if speed >= 1:
        first, second = list(range(100)), sorted({100 + round(speed * k) for k in range(int(100 / speed) + 1)
                                                  if 100 + round(speed * k) < 200})
        elsewhere = []
    else:
        first = sorted({round(k / speed) for k in range(int(100 * speed) + 1) if round(k / speed) < 100})
        second, elsewhere = list(range(100, 200)), list(open_sequence(KITTI90.parent / "07").frames)[:ELSEWHERE]
    frames = list(open_sequence(KITTI90).frames)
    name = f"k90_{speed:.3g}x_{'full' if size is None else f'{size[0]}x{size[1]}'}{'_darker' if darker else ''}"
    rng = np.random.default_rng(0)
    transform = (lambda image: darken(image, rng, **DARKER)) if darker else None
    sources = [frames[i] for i in first] + elsewhere + [frames[i] for i in second]
    keep = first + [-1] * len(elsewhere) + second
    return plain_folder(out / name, sources, size, transform, len(first) + len(elsewhere)), keep


def scored(run: Path, keep: list[int]) -> dict[str, Any]:
    """Loops of a run folder in KITTI 90's frame numbers (``keep``: -1 for a KITTI 07 frame): how many, how many
    false, the metres from each false loop's query to its keyframe (``poses/90.txt``, ground plane x-z; none for a
    KITTI 07 frame), and how many second-pass frames have a true loop among the frames written."""
    from cae_lcd.evaluation.ground_truth import read_loop_pairs
    from retrieval.run_folder import RunFolder

    truth = {tuple(sorted(p)) for p in read_loop_pairs(KITTI90 / "loops.txt").tolist()}
    poses = np.loadtxt(KITTI90.parents[1] / "poses" / "90.txt").reshape(-1, 3, 4)[:, [0, 2], 3]
    loops = [(keep[q], keep[r]) for q, r in RunFolder(run).read_loops()[:, :2].astype(int).tolist()]
    false = [p for p in loops if min(p) < 0 or tuple(sorted(p)) not in truth]
    off = [float(np.linalg.norm(poses[q] - poses[r])) for q, r in false if min(q, r) >= 0]
    written = {f for f in keep if f >= 0}
    return {"loops": len(loops), "false": len(false), "off": off,
            "queries": len({max(p) for p in truth if max(p) >= 100 and p[0] in written and p[1] in written})}


def main(out: str | Path, write: bool = True) -> dict[str, dict[str, dict[str, Any]]]:
    """Runs every (set, variant); rewrites the ``revisit_speed`` section of BENCHMARKS.md when ``write``."""
    from .common import detect_run
    from .run import write_section

    out = Path(out)
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for speed in SPEEDS:
        for size_name, (size, darker) in SIZES.items():
            folder, keep = speed_folder(out, speed, size, darker)
            label = f"second pass at {speed:.3g}x, {size_name}"
            results[label] = {}
            for variant, conf in VARIANTS.items():
                summary = detect_run(folder, out / f"{folder.name}_{len(results[label])}", conf)
                res = scored(summary["out"], keep)
                res["ms"] = summary["ms_per_frame"]["total"]["median"]
                results[label][variant] = res
                log.info("%s, %s: %s", label, variant, res)
    body = ("### A revisit at another speed (`python -m bench.revisit_speed`, issue 27)\n\n"
            + (__doc__ or "").split("\n\n")[1].replace("\n", " ").replace("``", "`") + "\n\n"
            + md_table(["set", "queries with a true loop",
                        *(f"{v}: loops / false (metres off)" for v in VARIANTS), *(f"{v}: ms/frame" for v in VARIANTS)],
                       [[label, str(next(iter(row.values()))["queries"]),
                         *(_cell(row[v]) for v in VARIANTS), *(f"{row[v]['ms']:.1f}" for v in VARIANTS)]
                        for label, row in results.items()]) + "\n")
    if write:
        write_section(REPO / "BENCHMARKS.md", body, "revisit_speed")
    return results


def _cell(res: dict[str, Any]) -> str:
    """``loops / false (metres off: min-max)``."""
    off = f" ({min(res['off']):.0f}-{max(res['off']):.0f} m)" if res["off"] else ""
    return f"{res['loops']} / {res['false']}{off}"


if __name__ == "__main__":
    work_study_cli(main, __doc__, "runs/bench/revisit_speed")
