"""Rebuilds the bundled sample ``retrieval/sample`` from ``../shared/datasets/kitti/sequences/90``:
``python -m cae_lcd.evaluation.make_sample``. It lives here, not beside the sample, because it derives the sample's ground
truth from poses (``cae_lcd.evaluation.ground_truth``).

Every second frame of sequence 90 (100 frames: indices 0-49 are the first pass, 50-99 the second pass over the
same road), downscaled to half resolution and stored as JPEG (quality 90), with ``calib.txt`` (intrinsics scaled
to the new size), ``times.txt``, ``poses.txt`` and ``loops.txt`` (every pair under 5 m apart on the ground plane
and at least 50 frames apart, the rule of the source sequence).
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import cv2
import numpy as np

from retrieval.detect import SAMPLE_DIR
from retrieval.sequences import open_sequence

from .ground_truth import loops_from_poses

HERE = SAMPLE_DIR
STEP, SCALE, QUALITY = 2, 0.5, 90


def main(source: Path, out: Path = HERE) -> None:
    seq = open_sequence(source)
    keep = np.arange(0, len(seq), STEP)
    if (out / "image_0").exists():
        shutil.rmtree(out / "image_0")
    (out / "image_0").mkdir(parents=True)
    for new, old in enumerate(keep):
        img = cv2.imread(str(seq.frames[old]), cv2.IMREAD_UNCHANGED)
        small = cv2.resize(img, None, fx=SCALE, fy=SCALE, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(out / "image_0" / f"{new:06d}.jpg"), small, [cv2.IMWRITE_JPEG_QUALITY, QUALITY])
    K = seq.K.copy()
    K[:2, :2] *= SCALE
    K[:2, 2] = (K[:2, 2] + 0.5) * SCALE - 0.5  # pixel centres move with the scale
    P = np.hstack([K, np.zeros((3, 1))])
    (out / "calib.txt").write_text("P0: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n")
    np.savetxt(out / "times.txt", seq.timestamps[keep], fmt="%.6e")
    poses = seq.poses[keep]
    np.savetxt(out / "poses.txt", poses.reshape(len(keep), 12), fmt="%.9e")
    pairs = loops_from_poses(poses, radius=5.0, min_gap=50)
    np.savetxt(out / "loops.txt", pairs, fmt="%d")
    (out / "frames.txt").write_text("# sample_index sequence_90_index\n" +
                                    "".join(f"{i} {o}\n" for i, o in enumerate(keep)))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", type=Path, default=Path("../shared/datasets/kitti/sequences/90"))
    main(ap.parse_args().source)
