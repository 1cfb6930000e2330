"""Headless plots of rollouts (matplotlib's Agg backend: no display needed, PNG out).

Inputs are plain arrays in physical units, so any caller (training, `mpnode evaluate`) can
draw them; these functions only draw and save.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # before pyplot: servers and CI have no display

import matplotlib.pyplot as plt
import numpy as np

MAX_NODES = 6  # columns of a rollout figure; larger graphs show their first nodes


def plot_rollout(time, true, pred, messages, state_names: Sequence[str], path: str | Path,
                 *, title: str = "") -> Path:
    """Predicted vs true states per node, message norms beneath (the paper's Fig. 2).

    Args:
        time: `[T]` sample times.
        true, pred: `[T, N, D]` one trajectory in physical units.
        messages: `[T, N, M]` the model's message states, or None.
        state_names: `[D]` labels of the rows.
        path: PNG to write (its folder is created).
        title: figure title.

    Returns:
        The path written.
    """
    time, true, pred = _np(time), _np(true), _np(pred)
    nodes, dims = min(true.shape[1], MAX_NODES), true.shape[2]
    shown = (f"all {nodes} nodes" if nodes == true.shape[1]
             else f"nodes 0–{nodes - 1} of {true.shape[1]}")
    title = f"{title} · {shown}" if title else shown
    has_msg = messages is not None and _np(messages).shape[-1] > 0
    rows = dims + int(has_msg)
    fig, axes = plt.subplots(rows, nodes, figsize=(2.6 * nodes + 0.8, 1.8 * rows + 0.6),
                             sharex=True, squeeze=False)
    for i in range(nodes):
        axes[0, i].set_title(f"node {i}", fontsize=9)
        for d in range(dims):
            ax = axes[d, i]
            ax.plot(time, true[:, i, d], color="k", lw=1.2, label="true")
            ax.plot(time, pred[:, i, d], color="tab:red", lw=1.2, ls="--", label="predicted")
            if i == 0:
                ax.set_ylabel(state_names[d] if d < len(state_names) else f"x{d}")
        if has_msg:
            norm = np.linalg.norm(_np(messages)[:, i], axis=-1)  # (T,)
            axes[dims, i].plot(time, norm, color="tab:blue", lw=1.2)
            if i == 0:
                axes[dims, i].set_ylabel("‖message‖")
        axes[rows - 1, i].set_xlabel("t")
    axes[0, 0].legend(fontsize=7, loc="best")
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path)


def plot_error_vs_time(time, mse_vs_time, path: str | Path, *, labels: Sequence[str] = (),
                       title: str = "rollout error vs time") -> Path:
    """Normalized MSE against time, log scale; t₀ (exact by construction) is left out.

    Args:
        time: `[T]`.
        mse_vs_time: `[T]`, or `[C, T]` for C curves named by `labels`.
        path: PNG to write.
    """
    time, curves = _np(time), np.atleast_2d(_np(mse_vs_time))
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for c, curve in enumerate(curves):
        label = labels[c] if c < len(labels) else None
        ax.plot(time[1:], curve[1:], lw=1.4, label=label)
    ax.set_yscale("log")
    ax.set_xlabel("t")
    ax.set_ylabel("MSE (normalized)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    if labels:
        ax.legend(fontsize=8)
    return _save(fig, path)


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x, dtype=float)


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
