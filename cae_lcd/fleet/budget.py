"""The verification budget of a keyframe: which other robots' candidates are verified when there are many robots.

Searching every other robot costs little (a cosine top-k each); verifying a candidate (SIFT matching + RANSAC) costs
milliseconds, so with N robots and k candidates each a keyframe would cost k (N - 1) verifications. Like the
multi-robot systems of the field, a keyframe gets a fixed budget: the ``budget`` candidates with the highest
similarity over all other robots, each robot's own top-``k`` first (a robot never gets more than ``k``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["shortlist"]


def shortlist(scores: dict[str, np.ndarray], k: int, min_score: float, budget: int) -> dict[str, np.ndarray]:
    """The candidates to verify, per other robot.

    Args:
        scores: ``{robot: (n_robot,) similarities}`` of the query against each other robot's keyframes.
        k: at most this many candidates per robot (its best). min_score: candidates under it are not verified.
        budget: at most this many candidates in all (the most similar first; ties: robot name, then position);
            0: no bound.

    Returns:
        ``{robot: (m,) positions into its scores, best first}``, only robots with at least one candidate.
    """
    pool: list[tuple[float, str, int]] = []
    for robot, sims in scores.items():
        sims = np.asarray(sims, np.float64).reshape(-1)
        top = np.argsort(-sims, kind="stable")[:k]
        pool += [(-float(sims[i]), robot, int(i)) for i in top if sims[i] >= min_score]
    pool.sort()
    chosen: dict[str, list[int]] = {}
    for _, robot, i in pool[:budget] if budget > 0 else pool:
        chosen.setdefault(robot, []).append(i)
    return {robot: np.asarray(ids, np.int64) for robot, ids in chosen.items()}
