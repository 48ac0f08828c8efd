"""Do the loop edges a back end gets agree with the ground truth? ``python -m bench.loop_edges [--no-write]``.

Runs ``cae-lcd detect`` (default config) on KITTI 90 from ``../shared`` and on the bundled sample, loads each run's
``loop_edges.g2o`` in gtsam (``readG2o``) and compares every edge's rotation and translation direction with the
relative pose of the ground-truth poses (``retrieval.edges.edge_errors``); writes the ``loop-edges`` section of
BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

import numpy as np

from retrieval.detect import SAMPLE_DIR
from retrieval.edges import ROTATION_SIGMA_1, edge_errors
from retrieval.run_folder import RunFolder
from retrieval.sequences import open_sequence

from .common import detect_run, md_table
from .run import write_section

__all__ = ["main", "edge_report"]

log = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[1]
KITTI_90 = REPO.parent / "shared" / "datasets" / "kitti" / "sequences" / "90"


def edge_report(out: str | Path, sequence: str | Path) -> dict[str, Any]:
    """Errors of a run folder's loop edges against the sequence's poses: counts and rotation / translation-direction
    error percentiles (degrees), and the share of edges within 3 sigma of the information rule."""
    import gtsam

    run = RunFolder(Path(out))
    graph, _ = gtsam.readG2o(str(run.edges_g2o), True)
    edges = run.read_edge_list()
    err = edge_errors(edges, open_sequence(sequence).poses)
    sigma = np.degrees(ROTATION_SIGMA_1 / np.sqrt([max(e.inliers, 1) for e in edges]))
    rot, trans = err[:, 0], err[:, 1]
    pct = (lambda a, q: float(np.nanpercentile(a, q)) if len(a) else float("nan"))
    return {"loops": len(run.read_loops()), "edges": len(edges), "g2o_factors": int(graph.size()),
            "rot_median": pct(rot, 50), "rot_p90": pct(rot, 90), "rot_max": pct(rot, 100),
            "trans_dir_median": pct(trans, 50), "trans_dir_p90": pct(trans, 90),
            "within_3_sigma": float(np.mean(rot <= 3 * sigma)) if len(edges) else float("nan"),
            "median_inliers": float(np.median([e.inliers for e in edges])) if edges else float("nan")}


def main(out: str | Path = "runs/bench/loop_edges", write: bool = True) -> dict[str, dict[str, Any]]:
    """Runs the two sequences and returns their ``edge_report`` by name (and writes BENCHMARKS.md's section)."""
    results = {}
    for name, seq in (("KITTI 90", KITTI_90), ("bundled sample", SAMPLE_DIR)):
        folder = Path(out) / name.replace(" ", "_")
        summary = detect_run(seq, folder)
        results[name] = edge_report(folder, seq) | {"wall_s": summary["wall_s"]}
        log.info("%s: %s", name, results[name])
    rows = [[name, r["loops"], r["edges"], r["g2o_factors"], r["median_inliers"], r["rot_median"], r["rot_p90"],
             r["rot_max"], r["trans_dir_median"], r["trans_dir_p90"], r["within_3_sigma"]]
            for name, r in results.items()]
    body = ("## Loop edges against the ground truth (`python -m bench.loop_edges`)\n\n"
            "Each accepted loop's relative pose from `loop_edges.g2o` (loaded with `gtsam.readG2o`) against "
            "`poses[match]^-1 poses[query]` of the ground truth; degrees. The translation is compared by direction "
            "(it is known up to scale). Within 3 sigma: the share of edges whose rotation error is within 3x the "
            "standard deviation of the information rule (`retrieval/edges.py`: 0.1 rad / sqrt(inliers)). Default "
            "config, measured under load on 2 shared cores.\n\n"
            + md_table(["sequence", "loops", "edges", "g2o factors", "median inliers", "rotation median",
                        "rotation p90", "rotation max", "t direction median", "t direction p90", "within 3 sigma"],
                       rows))
    if write:
        write_section(REPO / "BENCHMARKS.md", body, "loop-edges")
    return results


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/bench/loop_edges", help="work folder (rewritten)")
    ap.add_argument("--no-write", action="store_true", help="do not rewrite BENCHMARKS.md")
    args = ap.parse_args()
    main(args.out, not args.no_write)
