"""A quadrotor-swarm flight in 3-D: quads, cables, load and the doorway (headless, PNG out).

Inputs are one stored flight's arrays (`states`, `hidden/load`, optionally
`hidden/load_reference`), so this draws a dataset file's flight, a model's rollout, or a
simulation alike. Called by `examples/render_flight.py`.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # before pyplot: servers and CI have no display

import matplotlib.pyplot as plt
import numpy as np

from mpnode_cli.report.plots import save_whole

# The doorway of the RA-L set-up (TrajectoryOptimization.jl `examples/RA-L/problem.jl`;
# docs/quadrotor.md), as `systems/quadrotor_flight.py` checks it; repeated because reports
# sit below systems and do not import them.
CYLINDERS = ((2.5, 1.0), (2.5, -1.0), (3.0, 1.0), (3.0, -1.0))
CYLINDER_RADIUS = 0.5
CEILING = 2.1


def plot_flight(states, load, path: str | Path, *, reference=None, time=None, snapshots: int = 6,
                title: str = "") -> Path:
    """Draw one flight: paths, a few snapshots of quads, cables and load, and the doorway.

    Args:
        states: `[T, N, ≥3]` quad states (position first).
        load: `[T, ≥3]` load states (position first).
        path: PNG to write (its folder is created).
        reference: `[T, 3]` the planned load path, drawn dotted, or None.
        time: `[T]` sample times, for the snapshot labels; None labels sample indices.
        snapshots: how many instants to draw, evenly spread along the load's path (first and
            last included).
        title: figure title.

    Returns:
        The path written.
    """
    quads = np.asarray(states, dtype=float)[..., :3]  # [T, N, 3]
    load = np.asarray(load, dtype=float)[..., :3]  # [T, 3]
    steps, n = quads.shape[:2]
    fig = plt.figure(figsize=(12.0, 6.0))
    ax = fig.add_subplot(projection="3d")
    _doorway(ax)

    colors = plt.get_cmap("tab10")(np.arange(n) % 10)
    for i in range(n):
        ax.plot(*quads[:, i].T, color=colors[i], lw=0.8, alpha=0.6)
    ax.plot(*load.T, color="k", lw=1.4, label="load")
    if reference is not None:
        ax.plot(*np.asarray(reference, dtype=float)[:, :3].T, color="k", lw=0.8, ls=":",
                label="load reference")  # fmt: skip

    # Snapshots evenly spaced along the load's path (not in time: it hovers while the
    # formation folds and opens), so that they do not overlap.
    travelled = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(load, axis=0), axis=1))))
    marks = np.linspace(0.0, travelled[-1], max(snapshots, 2))
    picks = np.unique(np.minimum(np.searchsorted(travelled, marks), steps - 1))
    for k in picks:
        for i in range(n):
            ax.plot(*np.stack((load[k], quads[k, i])).T, color="0.35", lw=0.7)
        ax.scatter(*quads[k].T, color=colors, s=18, depthshade=False)
        ax.scatter(*load[k], color="k", s=30, depthshade=False)
        label = f"t={time[k]:g}" if time is not None else f"k={k}"
        ax.text(load[k, 0], load[k, 1], load[k, 2] - 0.2, label, fontsize=8, ha="center",
                va="top")  # fmt: skip

    lo = np.minimum(quads.reshape(-1, 3).min(0), load.min(0)) - 0.3
    hi = np.maximum(quads.reshape(-1, 3).max(0), load.max(0)) + 0.3
    lo[1], hi[1] = min(lo[1], -1.6), max(hi[1], 1.6)
    lo[2], hi[2] = 0.0, CEILING
    ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]),
           xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")  # fmt: skip
    # True proportions, with height doubled so that the fan and the ceiling read clearly.
    ax.set_box_aspect((hi[0] - lo[0], hi[1] - lo[1], 2 * (hi[2] - lo[2])), zoom=1.25)
    ax.view_init(elev=22, azim=-58)
    ax.legend(loc="upper left", fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    return save_whole(fig, path, dpi=100, bbox_inches="tight")


def _doorway(ax) -> None:
    """The four cylinders up to the ceiling, and the ceiling's outline over the doorway."""
    angle, z = np.meshgrid(np.linspace(0, 2 * np.pi, 24), np.array([0.0, CEILING]))
    for cx, cy in CYLINDERS:
        ax.plot_surface(cx + CYLINDER_RADIUS * np.cos(angle), cy + CYLINDER_RADIUS * np.sin(angle),
                        z, color="tab:gray", alpha=0.25, linewidth=0)  # fmt: skip
    x = np.array([2.0, 3.5, 3.5, 2.0, 2.0])
    y = np.array([-1.5, -1.5, 1.5, 1.5, -1.5])
    ax.plot(x, y, np.full_like(x, CEILING), color="tab:gray", lw=0.8, ls="--")
