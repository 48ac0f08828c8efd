"""The fleet's trajectories before and after the merge (PNG, matplotlib's Agg canvas, no pyplot)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

__all__ = ["plot_merge"]

_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def plot_merge(path: str | Path, local: dict[str, np.ndarray], merged: dict[str, np.ndarray],
               truth: dict[str, np.ndarray] | None = None) -> Path:
    """Two panels, x-z (KITTI's ground plane): each robot's trajectory in its own map, then in the global frame.

    Args:
        path: PNG to write.
        local: robot -> ``(N, 3)`` camera positions in its own map.
        merged: robot -> ``(M, 3)`` corrected positions in the global frame (robots not merged are absent).
        truth: robot -> ``(N, 3)`` ground-truth positions in the global frame, drawn dashed on the right.

    Returns:
        ``path``.
    """
    fig = Figure(figsize=(11, 5))
    before, after = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    for i, (robot, xyz) in enumerate(sorted(local.items())):
        colour = _COLOURS[i % len(_COLOURS)]
        before.plot(xyz[:, 0], xyz[:, 2], "-", color=colour, label=f"{robot} (own map)")
        if robot in merged:
            after.plot(merged[robot][:, 0], merged[robot][:, 2], "-", color=colour, lw=2, label=f"{robot} merged")
        if truth and robot in truth:
            after.plot(truth[robot][:, 0], truth[robot][:, 2], "--", color="black", lw=0.8,
                       label="ground truth" if i == 0 else None)
    before.set_title("before: each robot in its own map")
    after.set_title("after: merged by the fleet server")
    for ax in (before, after):
        ax.set_xlabel("x")
        ax.set_ylabel("z")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    FigureCanvasAgg(fig)
    fig.savefig(path, dpi=100)
    return Path(path)
