"""Evaluation figures: trajectories and the paper's Fig. 5 heading-change maps."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402 - the backend must be chosen first
import numpy as np  # noqa: E402

from policy import features  # noqa: E402

# Fig. 5 scenarios: other agents as (north_m, east_m, heading_rad)
FIG5_SCENARIOS = {
    "two agents, other at (0,0) head-on": [(0.0, 0.0, math.pi)],
    "four agents": [(-20.0, -20.0, 0.0), (10.0, 10.0, math.pi), (20.0, 20.0, math.pi)],
}


def plot_tracks(tracks, goals, title, png) -> None:
    """tracks (T, N, 2) north/east with NaN after leaving; east is drawn to the right."""
    fig, ax = plt.subplots(figsize=(5, 5))
    n = tracks.shape[1]
    cmap = plt.get_cmap("hsv")
    for i in range(n):
        c = cmap(i / max(n, 1))
        ax.plot(tracks[:, i, 1], tracks[:, i, 0], lw=0.8, color=c)
        ax.plot(tracks[0, i, 1], tracks[0, i, 0], "o", ms=3, color=c)
        ax.plot(goals[i, 1], goals[i, 0], "x", ms=4, color=c)
    ax.set_aspect("equal")
    ax.set_xlabel("east (policy m)")
    ax.set_ylabel("north (policy m)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def heading_change_grid(pol, others, extent_m=30.0, cells=121):
    """Commanded heading change (deg, + = right) of an ego flying north with the goal
    far ahead, over a grid of ego positions; NaN inside the 3 m separation."""
    xs = np.linspace(-extent_m, extent_m, cells)
    north, east = np.meshgrid(xs, xs, indexing="ij")
    pos = np.stack([north.ravel(), east.ravel()], axis=1)
    g = pos.shape[0]
    heading = np.zeros(g)
    goal = pos + np.array([1000.0, 0.0])
    o = np.array(others, dtype=np.float64)
    nbr_pos = np.broadcast_to(o[:, :2], (g, len(o), 2))
    nbr_h = np.broadcast_to(o[:, 2], (g, len(o)))
    valid = np.ones((g, len(o)), bool)
    seq, lengths, gf, _ = features.observe_padded(
        pos, heading, goal, nbr_pos, nbr_h, valid, pol.obs_cfg, pol.max_neighbours
    )
    a = features.clip_unit(pol.net.head_forward(pol.net.lstm_last_batch(seq, lengths), gf))
    change = np.degrees(np.arctan2(a[:, 1], a[:, 0]))
    d = np.hypot(pos[:, None, 0] - o[None, :, 0], pos[:, None, 1] - o[None, :, 1]).min(axis=1)
    change[d < 3.0] = np.nan
    return north, east, change.reshape(north.shape)


def heading_change_maps(pol, png) -> None:
    """Both Fig. 5 scenarios side by side, colour scale -10..10 degrees."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    for ax, (title, others) in zip(axes, FIG5_SCENARIOS.items(), strict=True):
        north, east, ch = heading_change_grid(pol, others)
        im = ax.pcolormesh(east, north, ch, cmap="coolwarm", vmin=-10, vmax=10, shading="auto")
        for n_m, e_m, h in others:
            ax.annotate(
                "",
                xy=(e_m + 4 * math.sin(h), n_m + 4 * math.cos(h)),
                xytext=(e_m, n_m),
                arrowprops={"arrowstyle": "->", "color": "k"},
            )
            ax.plot(e_m, n_m, "ko", ms=4)
        ax.set_aspect("equal")
        ax.set_title(f"{title}\n(ego heading north, goal ahead)", fontsize=9)
        ax.set_xlabel("east (m)")
        ax.set_ylabel("north (m)")
    fig.colorbar(im, ax=axes, label="commanded heading change (deg, + = right)")
    fig.savefig(png, dpi=110)
    plt.close(fig)
