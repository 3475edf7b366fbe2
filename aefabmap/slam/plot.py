"""Top view (x-y of the ground-truth frame) of ground truth, odometry and optimised trajectories (matplotlib)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def plot_top_view(path: str | Path, trajectories: dict[str, np.ndarray], loops: list[tuple[int, int]] | None = None,
                  loop_positions: np.ndarray | None = None, title: str = "") -> None:
    """Save a PNG of the trajectories' positions seen from above.

    trajectories: label -> (N, 4, 4) poses, all in one frame (the estimates aligned to the ground
    truth); axes x, y of that frame (TUM's motion-capture frame has z up). loops: (a, b) frame
    pairs of loop edges, drawn as lines between their positions in loop_positions (N, 4, 4).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 6.0), dpi=120)
    styles = {"ground truth": {"color": "k", "lw": 2.0}, "odometry": {"color": "tab:red", "lw": 1.2, "ls": "--"},
              "optimised": {"color": "tab:blue", "lw": 1.5}}
    for label, poses in trajectories.items():
        xy = poses[:, :2, 3]
        ax.plot(xy[:, 0], xy[:, 1], label=label, **styles.get(label, {}))
        ax.plot(xy[0, 0], xy[0, 1], "o", color=styles.get(label, {}).get("color", "gray"), ms=4)
    if loops and loop_positions is not None:
        for n, (a, b) in enumerate(loops):
            p = loop_positions[[a, b], :2, 3]
            ax.plot(p[:, 0], p[:, 1], color="tab:green", lw=0.8, label="loop edges" if n == 0 else None)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
