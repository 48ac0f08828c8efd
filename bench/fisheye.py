"""A fisheye camera: KITTI 90 seen through an equidistant lens gives the pinhole run's loops and edge rotations?
``python -m bench.fisheye [--no-write]``.

Every frame of KITTI 90 is warped through an equidistant (Kannala-Brandt) model with KITTI's own ``K`` and
``FISHEYE`` coefficients (``fisheye_warp``: each fisheye pixel samples the pinhole image where its ray lands), the
camera written as a YAML file (``write_camera_yaml``), and ``cae-lcd detect --camera-info`` runs on the warped
frames; its loops and loop-edge rotations are compared with the pinhole run's on the original frames, and with the
warped frames detected as a pinhole (``--intrinsics``, no distortion: what a user without a camera model gets), and
with a control: the original frames ``BRIGHTER`` grey levels brighter (how many queries between two frames of the
first pass take the other one when the pixels barely change). Writes the ``fisheye`` section of BENCHMARKS.md.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .common import REPO, work_study_cli

__all__ = ["FISHEYE", "BRIGHTER", "fisheye_warp", "write_camera_yaml", "write_fisheye_sequence",
           "write_brighter_sequence", "rotation_gaps", "main"]

log = logging.getLogger(__name__)

KITTI_90 = REPO.parent / "shared" / "datasets" / "kitti" / "sequences" / "90"
FISHEYE = (-0.02, 0.01, 0.0, 0.0)  #: equidistant k1..k4 of the warped frames
BRIGHTER = 2  #: grey levels added to the control run's frames


def fisheye_warp(image: np.ndarray, K: np.ndarray, D: tuple[float, ...] = FISHEYE) -> np.ndarray:
    """``image`` (a pinhole camera ``K``) as an equidistant camera with the same ``K`` and coefficients ``D`` sees
    it, same size: each output pixel takes the input pixel its ray meets (bilinear; black outside)."""
    h, w = image.shape[:2]
    grid = np.stack(np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)), -1)
    pin = cv2.fisheye.undistortPoints(grid.reshape(-1, 1, 2), K, np.asarray(D, np.float64), P=K).reshape(h, w, 2)
    return cv2.remap(image, pin[..., 0].astype(np.float32), pin[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def write_camera_yaml(path: Path, K: np.ndarray, D: tuple[float, ...] = FISHEYE) -> Path:
    """The small documented camera file (``verify.camera``) of an equidistant camera."""
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    path.write_text(f"intrinsics: [{fx!r}, {fy!r}, {cx!r}, {cy!r}]\n"
                    f"distortion_model: equidistant\ndistortion_coefficients: {list(map(float, D))}\n")
    return path


def write_fisheye_sequence(seq: Any, out: Path, frames: list[int] | None = None) -> tuple[Path, Path]:
    """The frames of ``seq`` (all, or ``frames``) warped into ``out/image_0`` (a plain folder, PNG: lossless),
    and the camera YAML beside it; returns ``(folder, yaml)``."""
    folder = out / "images"
    folder.mkdir(parents=True, exist_ok=True)
    for n, i in enumerate(range(len(seq)) if frames is None else frames):
        cv2.imwrite(str(folder / f"{n:06d}.png"), fisheye_warp(seq.read_frame(i)[0], seq.K))
    return out, write_camera_yaml(out / "camera.yaml", seq.K)


def write_brighter_sequence(seq: Any, out: Path, levels: int = BRIGHTER) -> Path:
    """The frames of ``seq`` ``levels`` grey levels brighter (clipped) in ``out/images``: the control run (how often
    a query between two frames of the first pass takes the other one when its pixels barely change)."""
    folder = out / "images"
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(len(seq)):
        image = seq.read_frame(i)[0].astype(np.int16) + levels
        cv2.imwrite(str(folder / f"{i:06d}.png"), np.clip(image, 0, 255).astype(np.uint8))
    return folder


def rotation_gaps(a: list, b: list) -> np.ndarray:
    """Degrees between the rotations of edges of the same ``(query, match)`` in ``a`` and ``b``."""
    rb = {(e.query, e.match): e.R for e in b}
    return np.array([np.degrees(np.arccos(np.clip((np.trace(rb[(e.query, e.match)].T @ e.R) - 1) / 2, -1, 1)))
                     for e in a if (e.query, e.match) in rb])


def main(out: str | Path = "runs/bench/fisheye", write: bool = True) -> dict[str, Any]:
    """Runs the three detections and returns their comparison (and writes BENCHMARKS.md's section)."""
    from cae_lcd.evaluation.ground_truth import read_loop_pairs
    from retrieval.edges import edge_errors
    from retrieval.run_folder import RunFolder
    from retrieval.sequences import open_sequence

    from .common import detect_run, md_table
    from .run import write_section

    out = Path(out)
    seq = open_sequence(KITTI_90)
    folder, yaml_path = write_fisheye_sequence(seq, out / "kitti90_fisheye")
    intrinsics = {"intrinsics": ",".join(repr(float(v)) for v in (seq.K[0, 0], seq.K[1, 1], seq.K[0, 2], seq.K[1, 2]))}
    runs = {"pinhole, original frames": (KITTI_90, {}),
            "equidistant frames, --camera-info": (folder, {"camera_info": yaml_path}),
            "equidistant frames as a pinhole (--intrinsics)": (folder, intrinsics),
            f"control: pinhole frames {BRIGHTER} grey levels brighter": (
                write_brighter_sequence(seq, out / "kitti90_brighter"), intrinsics)}
    results, base = {}, None
    truth = {tuple(p) for p in read_loop_pairs(seq.ground_truth).tolist()}
    for name, (path, camera) in runs.items():
        run_dir = out / name.split(",")[0].replace(" ", "_").replace(":", "")
        summary = detect_run(path, run_dir, None, **camera)  # a fresh run: another round's weights resume nothing
        run = RunFolder(run_dir)
        loops = {tuple(map(int, r[:2])) for r in run.read_loops()}
        edges = run.read_edge_list()
        base = base or (loops, edges)
        gaps = rotation_gaps(edges, base[1])
        err = edge_errors(edges, seq.poses)[:, 0]
        pct = (lambda a, q: float(np.percentile(a, q)) if len(a) else float("nan"))
        near = {q: m for q, m in base[0]}
        results[name] = {"loops": len(loops), "correct": len(loops & truth), "same_loops": len(loops & base[0]),
                         "same_place": sum(q in near and abs(m - near[q]) <= 1 for q, m in loops),
                         "edges": len(edges), "rot_gap_median": pct(gaps, 50), "rot_gap_p90": pct(gaps, 90),
                         "rot_gap_max": pct(gaps, 100), "rot_err_median": pct(err, 50), "rot_err_max": pct(err, 100),
                         "worst_in_sigmas": float(err.max() / np.degrees(edges[int(err.argmax())].sigmas()[0]))
                         if len(err) else float("nan"),
                         "worst_pair": (edges[int(err.argmax())].query, edges[int(err.argmax())].match,
                                        edges[int(err.argmax())].inliers) if len(err) else None,
                         "wall_s": summary["seconds"]["frames"] + summary["seconds"]["calibration"]}
        log.info("%s: %s", name, results[name])
    body = ("## A fisheye camera (`python -m bench.fisheye`)\n\n"
            f"KITTI 90's 200 frames warped through an equidistant lens (KITTI's K, k1..k4 = {list(FISHEYE)}: "
            "`bench.fisheye.fisheye_warp`), detected with the camera's YAML (`--camera-info`: keypoints undistorted "
            "with `cv2.fisheye.undistortPoints` before the geometric check), against the pinhole run on the original "
            "frames: loops (correct: in `loops.txt`), the same (query, match) pairs as the pinhole run, the same "
            "query closing within one frame of the pinhole run's match (a query between two frames of the first "
            "pass closes on the one with more inliers: a few inliers more or less on the warped frames and it "
            "takes the neighbour, both in `loops.txt`), the rotation between the two runs' edges of the same pair, "
            "and each run's edge rotations against the ground truth (degrees; the worst one also in units of the "
            "rotation sigma its own information gives: an edge that is off says so). Each edge's pose is RANSAC's "
            "refined on all its inliers (`verify.geometry.refined_pose`: robust Gauss-Newton on the Sampson "
            "residuals from RANSAC's and MAGSAC's essential matrix, the lower cost kept). Default config, measured "
            "under load.\n\n"
            + md_table(["run", "loops", "correct", "same pairs as pinhole", "same query within 1 frame", "edges",
                        "rotation gap median",
                        "gap p90", "gap max", "rotation error median", "error max", "error max / its sigma"],
                       [[k, r["loops"], r["correct"], r["same_loops"], r["same_place"], r["edges"], r["rot_gap_median"],
                         r["rot_gap_p90"], r["rot_gap_max"], r["rot_err_median"], r["rot_err_max"],
                         r["worst_in_sigmas"]]
                        for k, r in results.items()])
            + "\n\nThe edge through the lens farthest from the ground truth, with the camera's YAML (query, match, "
            "inliers): "
            f"{results['equidistant frames, --camera-info']['worst_pair']}. What made the gaps small (issue 30, "
            "measured when written): the pose refined on all the inliers (RANSAC's five-point pose: gap median "
            "0.20, p90 0.43, max 2.90), and the unsure edges made again at the extractor's own 512 px, their frames "
            "read again (`retrieval.edges.edge_features`; `loop_edges`' `precise`: a rotation sigma over "
            "`REDO_RATIO` = 2 x the run's median), not only on the calibrated run's 384 px "
            "(`calibration.features_px`): there, 198 -> 99 through the lens had 138 inliers and was 2.7 degrees off, "
            "its translation 45: the forward motion's second minimum (a sideways translation and a turned rotation) "
            "put as many of its 161 matches within 2 px as the true pose (143 against 144) and had the lower robust "
            "cost, so no estimator on those points could tell (its information said so: a rotation sigma of 1.2 "
            "degrees, 10x the median); at 512 px it has 231 inliers and is 0.08 degree off (gap max 2.75 -> 0.11; "
            "every edge made at 512 px: 0.11 too, the edges 4x the time). Masking the lens's "
            "black corners out of the keypoint detection changed nothing (on 512 px features the gaps are 0.10 "
            "degree at most with and without it). Read as a pinhole, the warped frames' rotations are as good at "
            "the median (a radial lens keeps the epipolar lines of a forward motion, radial lines through the "
            "centre) and worse at the worst pair. The control (the original frames "
            f"{BRIGHTER} grey levels brighter) says what the same-pair column is worth: a query that lies between "
            "two frames of the first pass closes on either when a few inliers move; the same query within one frame "
            "is what holds.\n")
    if write:
        write_section(REPO / "BENCHMARKS.md", body, "fisheye")
    return results


if __name__ == "__main__":
    work_study_cli(main, __doc__, "runs/bench/fisheye")
