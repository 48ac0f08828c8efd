"""The fleet demo: a server on loopback and two robots streaming real KITTI frames to it at once through the Python
client; the server must find where they overlap and recover the transform between their maps.

- ``overlap`` (the default): robot A streams the even frames of ``00`` with their ground-truth poses, robot B the
  odd frames with every pose expressed in another frame (``truth``: a known rotation, translation and scale applied:
  B's map is ``truth`` of the world, its poses rigid in B's units). Scored: the recovered map-to-global transform of B
  against ``truth^-1`` (rotation degrees, scale %, translation % of the trajectory length) and the merged trajectory.
- ``negative``: robot A on ``00``, robot B on ``07`` (they never meet): any overlap is a false one.
- ``hostile`` (with ``overlap``): the same two robots, then again with a third robot H streaming garbage at the same
  time (``hostile_stream``: random rigid poses, images that are random noise or real ``00`` frames replayed out of
  place). Scored as well: how far H moves A's and B's solved keyframes (``hostile.moved_m``: the final graph solved
  with and without H's keyframes and edges; the bar is 0.1 m), and, for scale, how far they differ from the run
  without H (``hostile.run_to_run_m``: arrival order alone changes which overlap edges form).

The demo's robots send 2-100 keyframes each, within a detector's online warm-up (``2 x search.exclude_recent`` = 100
keyframes, in which a robot accepts nothing: ``cae_lcd.fleet.recognition``): the demo's server runs the fixed policy
(``DEMO_RECOGNITION``), as the fleet did before its robots calibrated online.

``run_demo`` returns the summary it writes to ``OUT/fleet_demo.json``; ``OUT/trajectories.png`` shows both
trajectories before and after the merge; ``OUT/trajectories/NAME.tum`` and ``NAME.kitti`` are each robot's corrected
trajectory in the global frame (``cae_lcd.fleet.export``; e.g. ``evo_ape tum GT OUT/trajectories/B.tum``).
"""

from __future__ import annotations

import json
import logging
import secrets
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np

from cae_lcd.core.conf import ConfigError
from cae_lcd.core.errors import LCDError
from cae_lcd.core.files import prepare_out_dir, write_text_atomic
from retrieval.sequences import read_kitti_calib, read_kitti_poses, read_times

from .client import FleetClient
from .export import FORMATS, trajectory_rows, write_trajectory
from .graph import PoseGraph
from .plots import plot_merge
from .recognition import FIXED_POLICY
from .runner import ServerThread
from .server import create_app
from .sim3 import Sim3

__all__ = ["RobotStream", "kitti_stream", "run_demo", "DEMO_TRUTH", "DEMO_FORMAT_VERSION", "transform_errors"]

log = logging.getLogger(__name__)

DEMO_FORMAT_VERSION = 1  #: format of ``fleet_demo.json``
DEMO_RECOGNITION = FIXED_POLICY  #: the demo server's recognition conf (its streams are one warm-up long: module doc)
#: where robot B's map lies: B's map = DEMO_TRUTH(world); scale 2 (B's units are half metres), 40 deg about a
#: tilted axis, an offset of tens of metres
DEMO_TRUTH = Sim3(2.0, cv2.Rodrigues(np.array([0.1, 0.65, -0.15]))[0], np.array([40.0, -5.0, 25.0]))


@dataclass
class RobotStream:
    """What one robot sends: keyframe ids (the frame numbers), image files, local ``(N, 4, 4)`` poses, times."""

    name: str
    frames: list[int]
    images: list[Path]
    poses: np.ndarray
    times: np.ndarray
    K: np.ndarray


def kitti_stream(name: str, kitti_root: str | Path, sequence: str, frames: list[int],
                 truth: Sim3 | None = None) -> RobotStream:
    """A robot streaming frames of a KITTI sequence; its poses are ``truth o pose o (1 / truth.s)`` when ``truth``
    is given (the same camera path in another map, rigid poses in that map's units), else the ground truth.

    Raises:
        ConfigError: missing or malformed sequence files.
    """
    root = Path(kitti_root)
    seq = root / "sequences" / sequence
    gt = read_kitti_poses(root / "poses" / f"{sequence}.txt")
    poses = []
    for f in frames:
        P = Sim3.from_pose(gt[f])
        if truth is not None:
            P = truth.compose(P).compose(Sim3(1.0 / truth.s, np.eye(3), np.zeros(3)))
        poses.append(P.matrix())
    return RobotStream(name, list(frames), [seq / "image_0" / f"{f:06d}.png" for f in frames], np.stack(poses),
                       read_times(seq / "times.txt")[frames], read_kitti_calib(seq / "calib.txt"))


def hostile_stream(name: str, kitti_root: str | Path, folder: str | Path, keyframes: int = 60,
                   seed: int = 19) -> RobotStream:
    """A robot that sends garbage: random rigid poses (anywhere within 1 km), and images that are random noise
    (even keyframes) or real frames of ``00`` picked at random (odd ones: they match A's and B's, with poses that
    agree with nothing); the noise images are written to ``folder``."""
    rng = np.random.default_rng(seed)
    real = kitti_stream(name, kitti_root, "00", sorted(rng.choice(200, keyframes, replace=False).tolist()))
    Path(folder).mkdir(parents=True, exist_ok=True)
    images, poses = [], []
    for k in range(keyframes):
        if k % 2 == 0:
            path = Path(folder) / f"noise{k:04d}.png"
            cv2.imwrite(str(path), rng.integers(0, 256, (376, 1241), dtype=np.uint8))
            images.append(path)
        else:
            images.append(real.images[k])
        poses.append(Sim3(1.0, cv2.Rodrigues(rng.normal(0, 2.0, 3))[0], rng.uniform(-1000, 1000, 3)).matrix())
    return RobotStream(name, list(range(keyframes)), images, np.stack(poses), np.arange(keyframes, dtype=float),
                       real.K)


def _stream(url: str, token: str, robot: RobotStream, failures: list[str], refused: dict[str, int]) -> None:
    """Submits every keyframe of ``robot`` in order (a thread's body): a refusal ends the robot's stream and is
    recorded in ``failures``, or, for a robot named in ``refused``, is counted there and the next keyframe sent."""
    client = FleetClient(url, token, timeout=120.0)
    for i, frame in enumerate(robot.frames):
        try:
            client.submit_keyframe(robot.name, frame, float(robot.times[i]), robot.poses[i],
                                   robot.images[i].read_bytes(), robot.K)
        except (LCDError, OSError) as err:
            if robot.name not in refused:
                failures.append(f"robot {robot.name}: {err}")
                return
            refused[robot.name] += 1


def transform_errors(found: Sim3, truth: Sim3, length: float) -> dict[str, float]:
    """Rotation (degrees), scale (%) and translation (% of ``length``) errors of a recovered transform."""
    angle, scale, trans = found.errors(truth)
    return {"rotation_error_deg": angle, "scale_error_pct": 100.0 * scale,
            "translation_error_pct": 100.0 * trans / length, "translation_error_m": trans}


def _path_length(poses: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum())


def _stream_all(url: str, admin: FleetClient, robots: list[RobotStream]) -> tuple[float, dict[str, int]]:
    """Registers the robots and streams them at once; returns the wall time in seconds and, per robot after the
    first two, how many of its keyframes were refused (each refused one is skipped).

    Raises:
        LCDError: a keyframe of the first two robots was refused.
    """
    tokens = [admin.register(r.name) for r in robots]
    failures: list[str] = []
    refused = {r.name: 0 for r in robots[2:]}
    threads = [threading.Thread(target=_stream, args=(url, t, r, failures, refused), name=f"robot-{r.name}")
               for t, r in zip(tokens, robots)]
    started = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if failures:
        raise LCDError("; ".join(failures))
    return time.perf_counter() - started, refused


def _score(admin: FleetClient, robots: list[RobotStream], truth: Sim3 | None,
           world: np.ndarray) -> dict[str, Any]:
    """The summary: overlaps, transforms, errors against ``truth`` and the merged B trajectory's error."""
    transforms = admin.transforms(wait=True)
    a, b = robots
    out: dict[str, Any] = {"overlaps": admin.overlaps(), "merged": {"A", "B"} <= set(transforms),  # one frame
                           "loops": len([e for e in admin.loops("A") + admin.loops("B") if e["kind"] == "loop"]),
                           "keyframes": {r.name: len(r.frames) for r in robots}}
    out["overlap_edges"] = len([e for e in admin.loops("B") if e["kind"] == "overlap"])
    if truth is None:
        out["false_overlaps"] = len(out["overlaps"])
        return out
    length = _path_length(world)
    out["trajectory_length_m"] = length
    if not {"A", "B"} <= set(transforms):
        return out
    T = Sim3.from_matrix(transforms["A"]).inverse().compose(Sim3.from_matrix(transforms["B"]))  # B's map -> A's
    out.update(transform_errors(T, truth.inverse(), length))
    out["transform_B_to_A"] = T.matrix().tolist()
    poses = admin.poses("B", wait=True)
    merged = np.array([poses[f][:3, 3] for f in b.frames if f in poses])
    true = np.array([world[b.frames.index(f)][:3, 3] for f in b.frames if f in poses])
    out["merged_b_rmse_m"] = float(np.sqrt(((merged - true) ** 2).sum(1).mean()))
    out["merged_b_rmse_pct"] = 100.0 * out["merged_b_rmse_m"] / length
    return out


def _export(folder: Path, robots: list[RobotStream], merged: dict[str, dict[int, np.ndarray]]) -> dict[str, str]:
    """Writes each merged robot's corrected trajectory as ``folder/NAME.tum`` and ``NAME.kitti``; returns their
    paths by ``NAME.format``."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for r in robots:
        if merged.get(r.name):
            _, times, poses = trajectory_rows(merged[r.name], dict(zip(r.frames, r.times.tolist())))
            for fmt in FORMATS:
                out[f"{r.name}.{fmt}"] = str(write_trajectory(folder / f"{r.name}.{fmt}", times, poses, fmt))
    return out


def _session(state: Path, token: str, robots: list[RobotStream], truth: Sim3 | None,
             world_b: np.ndarray, while_serving: Callable[[str, str], None] | None = None
             ) -> tuple[dict[str, Any], dict[str, dict[int, np.ndarray]], float]:
    """A server over ``state``, the robots streaming at once (A and B must be accepted; a third robot's refusals
    are counted in ``summary["refused"]``; ``while_serving(url, token)`` is called once they have streamed, while
    the server still runs); returns ``(summary, merged poses per robot, wall s)``."""
    with ServerThread(create_app(state, token, recognition=DEMO_RECOGNITION)) as server:
        admin = FleetClient(server.url, token, timeout=120.0)
        wall, refused = _stream_all(server.url, admin, robots)
        if while_serving is not None:
            while_serving(server.url, token)
        summary = _score(admin, robots[:2], truth, world_b)
        summary["refused"] = refused
        merged = {r.name: admin.poses(r.name, wait=True) for r in robots}
        if len(robots) > 2:
            summary["moved_by_others_m"] = _moved_by(server.app.state.service.graph(), {r.name for r in robots[2:]})
    return summary, merged, wall


def _moved_by(graph: PoseGraph, others: set[str]) -> dict[str, float]:
    """How far ``others`` move each remaining robot's solved keyframes (m, largest): the graph solved with them
    against the same graph without them."""
    full, alone = graph.optimize(), graph.without(others).optimize()
    out: dict[str, float] = {}
    for n, T in alone.poses.items():
        gap = float(np.linalg.norm(T.t - full.poses[n].t)) if n in full.poses else float("inf")
        out[n.robot] = max(out.get(n.robot, 0.0), gap)
    return out


def _moved(before: dict[int, np.ndarray], after: dict[int, np.ndarray]) -> float:
    """Largest distance (m) between a keyframe's merged position in two runs (inf: merged in one run only)."""
    if set(before) != set(after):
        return float("inf")
    return max((float(np.linalg.norm(before[k][:3, 3] - after[k][:3, 3])) for k in before), default=0.0)


def run_demo(out: str | Path, kitti_root: str | Path, negative: bool = False, frames: int = 200,
             truth: Sim3 = DEMO_TRUTH, admin_token: str | None = None, hostile: bool = False,
             while_serving: Callable[[str, str], None] | None = None) -> dict[str, Any]:
    """Runs the demo (see the module doc) with a fresh server state in ``OUT/state``.

    Args:
        out: folder for ``fleet_demo.json``, ``trajectories.png``, ``trajectories/`` and the server's state
            (replaced).
        kitti_root: the KITTI folder (``sequences/``, ``poses/``).
        negative: robots on ``00`` and ``07`` instead (no overlap expected).
        frames: first frames of ``00`` used (robot A the even ones, B the odd ones; ``negative``: A the even ones
            of ``00``, B the even ones of ``07``).
        truth: robot B's map in the overlap demo (ignored with ``negative``).
        admin_token: the server's admin token (None: a random one).
        hostile: then run again with a third robot streaming garbage (``hostile_stream``) and score how far it
            moved A's and B's maps (``summary["hostile"]``).
        while_serving: called as ``while_serving(url, admin_token)`` once the robots have streamed, while the
            server still runs (e.g. a screenshot of its ``/map`` page: ``python -m bench.fleet_map``).

    Raises:
        ConfigError: bad KITTI files or ``out``. LCDError: a robot's keyframe was refused.
    """
    if not 4 <= frames <= 200:
        raise ConfigError(f"--frames must be in 4..200 (KITTI 00 here has 200 frames); got {frames}")
    out = prepare_out_dir(out)
    state = out / "state"
    if state.exists():
        shutil.rmtree(state)
    a = kitti_stream("A", kitti_root, "00", list(range(0, frames, 2)))
    if negative:
        b = kitti_stream("B", kitti_root, "07", list(range(0, min(frames, 160), 2)))
    else:
        b = kitti_stream("B", kitti_root, "00", list(range(1, frames, 2)), truth)
    world_b = kitti_stream("B", kitti_root, "07" if negative else "00", b.frames).poses
    token = admin_token or secrets.token_urlsafe(24)
    summary, merged, wall = _session(state, token, [a, b], None if negative else truth, world_b, while_serving)
    summary.update({"format_version": DEMO_FORMAT_VERSION, "mode": "negative" if negative else "overlap",
                    "wall_s": wall, "keyframes_per_s": (len(a.frames) + len(b.frames)) / wall,
                    "truth_B_map_from_world": None if negative else truth.matrix().tolist()})
    summary["trajectories"] = _export(out / "trajectories", [a, b], merged)
    if hostile:
        h = hostile_stream("H", kitti_root, out / "hostile_images", max(2, frames // 4))
        shutil.rmtree(out / "state_hostile", ignore_errors=True)
        attacked, moved_to, _ = _session(out / "state_hostile", token, [a, b, h], None if negative else truth,
                                         world_b)
        summary["hostile"] = {"keyframes": len(h.frames), "refused": attacked.get("refused", {}),
                              "moved_m": attacked["moved_by_others_m"],
                              "run_to_run_m": {r: _moved(merged[r], moved_to[r]) for r in ("A", "B")},
                              "errors_with_H": {k: v for k, v in attacked.items()
                                                if k.endswith(("_deg", "_pct", "_m")) and isinstance(v, float)},
                              "merged_H": bool(moved_to.get("H"))}
    write_text_atomic(out / "fleet_demo.json", json.dumps(summary, indent=2))
    plot_merge(out / "trajectories.png", {r.name: r.poses[:, :3, 3] for r in (a, b)},
               {name: np.array([p[:3, 3] for _, p in sorted(m.items())]) for name, m in merged.items() if m},
               {"A": a.poses[:, :3, 3], "B": world_b[:, :3, 3]})
    return summary
