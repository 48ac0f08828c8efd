"""Do the loop edges a back end gets agree with the ground truth, and help it? ``python -m bench.loop_edges
[--no-write]``.

Runs ``cae-lcd detect`` (default config) on KITTI 90 from ``../shared`` and on the bundled sample, loads each run's
``loop_edges.g2o`` in gtsam (``readG2o``) and compares every edge's rotation and translation direction with the
relative pose of the ground-truth poses (``retrieval.edges.edge_errors``). Then a pose graph in gtsam
(``pose_graph``): odometry from the ground truth with seeded noise (its noise model the noise drawn), a prior on the
first pose, and the loops as (a) none, (b) the g2o factors as written, (c) their rotations only (the marginal
rotation information, the translation unobserved), (d) the edges at the true length
(``retrieval.edges.metric_edges``); the end position error after Levenberg-Marquardt and the final chi-square
against its degrees of freedom (the rank the loop factors add). Writes the ``loop-edges`` section of BENCHMARKS.md.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from retrieval.detect import SAMPLE_DIR
from retrieval.edges import LENGTH_SIGMA, LoopEdge, edge_errors, g2o_order, metric_edges
from verify.geometry import UNOBSERVED_INFORMATION
from retrieval.run_folder import RunFolder
from retrieval.sequences import open_sequence

from .common import REPO, detect_run, md_table, work_study_cli
from .run import write_section

__all__ = ["main", "edge_report", "pose_graph", "ODOMETRY_SIGMAS", "VARIANTS"]

log = logging.getLogger(__name__)

KITTI_90 = REPO.parent / "shared" / "datasets" / "kitti" / "sequences" / "90"


ODOMETRY_SIGMAS = (0.01, 0.03)  #: drawn odometry noise a frame: rotation (rad, per axis), translation (m, per axis)
VARIANTS = ("no loops", "edges as written", "rotation only", "true scale")


def _rotation_only(e: LoopEdge) -> LoopEdge:
    """The edge with its marginal rotation information only (the translation unobserved)."""
    cov = np.linalg.inv(g2o_order(e.information()))
    info = np.zeros((6, 6))
    info[:3, :3] = np.linalg.inv(cov[:3, :3])
    info[3:, 3:] = np.eye(3) * UNOBSERVED_INFORMATION
    return LoopEdge(e.query, e.match, e.inliers, e.R, e.t, g2o_order(info))


def _rank(info: np.ndarray) -> int:
    """The dimensions an information matrix constrains (eigenvalues above 1e3 x the unobserved level)."""
    return int(np.sum(np.linalg.eigvalsh(info) > 1e3 * UNOBSERVED_INFORMATION))


def pose_graph(poses: np.ndarray, edges: list[LoopEdge], g2o: str | Path | None = None,
               seed: int = 0) -> dict[str, dict[str, float]]:
    """The drifted-odometry pose graph of ``poses`` ``(N, 3, 4)`` (ground truth, camera-to-world) with the loop
    edges of each of ``VARIANTS`` (``g2o``: the factors read from that file for "edges as written", else ``edges``
    as they are): end position error (m), chi-square and its degrees of freedom."""
    import gtsam

    rng = np.random.default_rng(seed)
    P = [gtsam.Pose3(np.vstack([p, [0, 0, 0, 1]])) for p in poses]
    s_rot, s_t = ODOMETRY_SIGMAS
    odo_noise = gtsam.noiseModel.Diagonal.Sigmas(np.r_[[s_rot] * 3, [s_t] * 3])
    base = gtsam.NonlinearFactorGraph()
    base.add(gtsam.PriorFactorPose3(0, P[0], gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    initial = gtsam.Values()
    initial.insert(0, P[0])
    for i in range(len(P) - 1):
        noisy = P[i].between(P[i + 1]).compose(
            gtsam.Pose3.Expmap(np.r_[rng.normal(0, s_rot, 3), rng.normal(0, s_t, 3)]))
        base.add(gtsam.BetweenFactorPose3(i, i + 1, noisy, odo_noise))
        initial.insert(i + 1, initial.atPose3(i).compose(noisy))
    loops: dict[str, list] = {"no loops": [], "rotation only": [_rotation_only(e) for e in edges],
                              "true scale": metric_edges(edges, poses), "edges as written": edges}
    out = {}
    for name in VARIANTS:
        graph = gtsam.NonlinearFactorGraph(base)
        if name == "edges as written" and g2o is not None:
            read, _ = gtsam.readG2o(str(g2o), True)
            graph.push_back(read)
        for e in loops[name] if not (name == "edges as written" and g2o is not None) else []:
            graph.add(gtsam.BetweenFactorPose3(e.match, e.query, gtsam.Pose3(gtsam.Rot3(e.R), e.t),
                                               gtsam.noiseModel.Gaussian.Information(g2o_order(e.information()))))
        result = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
        end = np.linalg.norm(result.atPose3(len(P) - 1).translation() - poses[-1][:3, 3])
        out[name] = {"end_error_m": float(end), "chi2": 2 * float(graph.error(result)),
                     "dof": sum(_rank(g2o_order(e.information())) for e in loops[name]), "factors": len(loops[name])}
    return out


def edge_report(out: str | Path, sequence: str | Path) -> dict[str, Any]:
    """Errors of a run folder's loop edges against the sequence's poses: counts and rotation / translation-direction
    error percentiles (degrees), and the share of edges within 3 sigma of the information rule."""
    import gtsam

    run = RunFolder(Path(out))
    graph, _ = gtsam.readG2o(str(run.edges_g2o), True)
    edges = run.read_edge_list()
    poses = open_sequence(sequence).poses
    err = edge_errors(edges, poses)
    sigma = np.degrees([e.sigmas()[0] for e in edges])
    rot, trans = err[:, 0], err[:, 1]
    pct = (lambda a, q: float(np.nanpercentile(a, q)) if len(a) else float("nan"))
    return {"loops": len(run.read_loops()), "edges": len(edges), "g2o_factors": int(graph.size()),
            "rot_median": pct(rot, 50), "rot_p90": pct(rot, 90), "rot_max": pct(rot, 100),
            "trans_dir_median": pct(trans, 50), "trans_dir_p90": pct(trans, 90),
            "within_3_sigma": float(np.mean(rot <= 3 * sigma)) if len(edges) else float("nan"),
            "median_inliers": float(np.median([e.inliers for e in edges])) if edges else float("nan"),
            "rot_sigma_median": pct(sigma, 50),
            "pose_graph": pose_graph(poses, edges, run.edges_g2o) if edges else {}}


def main(out: str | Path = "runs/bench/loop_edges", write: bool = True) -> dict[str, dict[str, Any]]:
    """Runs the two sequences and returns their ``edge_report`` by name (and writes BENCHMARKS.md's section)."""
    results = {}
    for name, seq in (("KITTI 90", KITTI_90), ("bundled sample", SAMPLE_DIR)):
        folder = Path(out) / name.replace(" ", "_")
        summary = detect_run(seq, folder)
        results[name] = edge_report(folder, seq) | {"wall_s": summary["wall_s"]}
        log.info("%s: %s", name, results[name])
    rows = [[name, r["loops"], r["edges"], r["g2o_factors"], r["median_inliers"], r["rot_median"], r["rot_p90"],
             r["rot_max"], r["rot_sigma_median"], r["trans_dir_median"], r["trans_dir_p90"], r["within_3_sigma"]]
            for name, r in results.items()]
    graph_rows = [[name, v, g["factors"], g["end_error_m"], g["chi2"], g["dof"]]
                  for name, r in results.items() for v, g in r["pose_graph"].items()]
    body = ("## Loop edges against the ground truth (`python -m bench.loop_edges`)\n\n"
            "Each accepted loop's relative pose from `loop_edges.g2o` (loaded with `gtsam.readG2o`) against "
            "`poses[match]^-1 poses[query]` of the ground truth; degrees. The translation is compared by direction "
            "(it is known up to scale). Within 3 sigma: the share of edges whose rotation error is within 3x the "
            "standard deviation the edge's information gives (`LoopEdge.sigmas`: the inliers' Sampson residuals, "
            "Gauss-Newton, times `MODEL_VARIANCE`; its median in the sigma column). Default config, measured under "
            "load on 2 shared cores.\n\n"
            + md_table(["sequence", "loops", "edges", "g2o factors", "median inliers", "rotation median",
                        "rotation p90", "rotation max", "rotation sigma median", "t direction median",
                        "t direction p90", "within 3 sigma"], rows)
            + "\n\nThe edges in a pose graph (gtsam, Levenberg-Marquardt): odometry from the ground truth with seeded "
            f"noise ({ODOMETRY_SIGMAS[0]} rad, {ODOMETRY_SIGMAS[1]} m a frame and axis; its noise model the noise "
            "drawn), a prior on the first pose; loops none, as written (`gtsam.readG2o` of `loop_edges.g2o`: rank 5, "
            "the translation's length unobserved), their rotations only (marginal rotation information), and at the "
            f"true length (`retrieval.edges.metric_edges` on the ground-truth poses, `cae-lcd detect --metric-edges`: "
            f"{LENGTH_SIGMA[0]:.0%} of the length along the translation, at least {LENGTH_SIGMA[1]} m). End error: "
            "the last pose's "
            "position, metres. Chi-square: the whole graph's at the optimum; dof: the rank the loop factors add "
            "(a consistent graph has chi-square near it).\n\n"
            + md_table(["sequence", "loops in the graph", "factors", "end error (m)", "chi-square", "dof"],
                       graph_rows))
    if write:
        write_section(REPO / "BENCHMARKS.md", body, "loop-edges")
    return results


if __name__ == "__main__":
    work_study_cli(main, __doc__, "runs/bench/loop_edges")
