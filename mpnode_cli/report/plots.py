"""Headless plots of rollouts (matplotlib's Agg backend: no display needed, PNG out).

Inputs are plain arrays in physical units, so any caller (training, `mpnode evaluate`) can
draw them; these functions only draw and save.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # before pyplot: servers and CI have no display

import matplotlib.pyplot as plt
import numpy as np

MAX_FIGURE_NODES = 6  # columns of a rollout figure; larger graphs show their first nodes
DPI = 110
# The naive predictors an error plot draws beside the model, as its tables name them
# (`mpnode_cli.training.baselines`).
BASELINE_LABELS = ("hold x(0)", "time mean (train)")


def plot_rollout(time, true, pred, messages, state_names: Sequence[str], path: str | Path,
                 *, title: str = "", dpi: int = DPI,
                 labels: tuple[str, str] = ("true", "predicted"), spread=None) -> Path:
    """Predicted vs true states per node, message norms beneath (the paper's Fig. 2).

    Args:
        time: `[T]` sample times.
        true, pred: `[T, N, D]` one trajectory in physical units, drawn solid and dashed;
            `pred` may be None (a file's trajectory drawn on its own).
        messages: `[T, N, M]` the model's message states, or None.
        state_names: `[D]` labels of the rows.
        path: PNG to write (its folder is created).
        title: figure title.
        dpi: resolution of the PNG.
        labels: the legend's names of `true` and `pred`: what they are (a prediction file
            holds a model's predictions, not the truth).
        spread: `[T, N, D]` an ensemble's members' std around `pred` (physical units),
            drawn as a light band of ± 2 std; None: no band.

    Returns:
        The path written.
    """
    time, true = _np(time), _np(true)
    curves = [(true, labels[0], {"color": "k"})]
    if pred is not None:
        curves.append((_np(pred), labels[1], {"color": "tab:red", "ls": "--"}))
    band = None if pred is None or spread is None else (_np(pred), 2 * _np(spread))
    nodes, dims = min(true.shape[1], MAX_FIGURE_NODES), true.shape[2]
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
            for states, label, style in curves:
                ax.plot(time, states[:, i, d], lw=1.2, label=label, **style)
            if band is not None:  # beneath the curves (a collection's zorder), listed after
                mean, width = band[0][:, i, d], band[1][:, i, d]
                ax.fill_between(time, mean - width, mean + width, color="tab:red", alpha=0.15,
                                lw=0, label="± 2 std (members)")
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
    return _save(fig, path, dpi)


def plot_error_vs_time(time, mse_vs_time, path: str | Path, *, labels: Sequence[str] = (),
                       title: str = "rollout error vs time", dpi: int = DPI) -> Path:
    """Normalized MSE against time, log scale; t₀ (exact by construction) is left out.

    Args:
        time: `[T]`.
        mse_vs_time: `[T]`, or `[C, T]` for C curves named by `labels` (evaluate's: the
            model's, then the baselines', `BASELINE_LABELS`, drawn dotted and grey).
        path: PNG to write.
    """
    time, curves = _np(time), np.atleast_2d(_np(mse_vs_time))
    fig, ax = plt.subplots(figsize=(5.5, 3.5))
    for c, curve in enumerate(curves):
        label = labels[c] if c < len(labels) else None
        style = ({"ls": ":", "color": "0.35" if label == BASELINE_LABELS[0] else "0.6"}
                 if label in BASELINE_LABELS else {})
        ax.plot(time[1:], curve[1:], lw=1.4, label=label, **style)
    ax.set_yscale("log")
    ax.set_xlabel("t")
    ax.set_ylabel("MSE (normalized)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    if labels:
        ax.legend(fontsize=8)
    return _save(fig, path, dpi)


def plot_curves(runs: dict[str, Sequence[dict]], path: str | Path, *, dpi: int = DPI,
                titles: Sequence[str] = ("training loss", "validation MSE (normalized)"),
                ) -> Path:
    """Training loss and validation MSE against epoch, one line per run (the paper's
    Fig. 3a, 4, 5, 7, 8, 9), log scale.

    Args:
        runs: label → a run's `metrics.jsonl` rows (`epoch`, `train_loss`, `val_mse`).
        titles: the two panels' (say the units when the rows are scaled).
    """
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.4))
    for label, rows in runs.items():
        for ax, key in zip(axes, ("train_loss", "val_mse"), strict=True):
            points = [(r["epoch"], r[key]) for r in rows if r.get(key) is not None]
            if points:
                ax.plot(*zip(*points, strict=True), lw=1.2, label=label)
    for ax, name in zip(axes, titles, strict=True):
        ax.set_yscale("log")
        ax.set_xlabel("epoch")
        ax.set_title(name, fontsize=10)
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7)
    return _save(fig, path, dpi)


def plot_bars(groups: dict[str, dict[str, float | None]], path: str | Path, *, ylabel: str,
              title: str = "", dpi: int = DPI,
              errors: dict[str, dict[str, float | None]] | None = None) -> Path:
    """Grouped bars on a log scale: group → {bar label → value} (a missing value: no bar),
    with `errors` (the same keys: each bar's std, e.g. over an ensemble's members) drawn as
    error bars."""
    # Wide enough for the title too (one group's bars alone would clip it).
    inches = max(1.2 + 1.4 * max(len(groups), 1), 1.0 + 0.085 * len(title))
    fig, ax = plt.subplots(figsize=(inches, 3.4))
    labels = list(dict.fromkeys(k for bars in groups.values() for k in bars))
    width = 0.8 / max(len(labels), 1)
    for j, label in enumerate(labels):
        xs = [i + (j - (len(labels) - 1) / 2) * width for i in range(len(groups))]
        ys = [bars.get(label) for bars in groups.values()]
        spread = [(errors or {}).get(group, {}).get(label) for group in groups]
        drawn = [i for i, y in enumerate(ys) if y]
        ax.bar([xs[i] for i in drawn], [ys[i] for i in drawn], width, label=label,
               yerr=[spread[i] or 0.0 for i in drawn] if errors else None, capsize=3)
    ax.set_xticks(range(len(groups)), list(groups))
    ax.set_yscale("log")
    ax.set_ylabel(ylabel, fontsize=8)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, axis="y", which="both")
    ax.legend(fontsize=7)
    return _save(fig, path, dpi)


def plot_components(time, scores, path: str | Path, *, title: str = "",
                    dpi: int = DPI) -> Path:
    """Principal components against time, one line per trajectory (the paper's Fig. 12).

    Args:
        time: `[T]`. scores: `[B, T, k]` the first k components of B trajectories.
    """
    time, scores = _np(time), _np(scores)
    k = scores.shape[-1]
    fig, axes = plt.subplots(1, k, figsize=(3.2 * k, 2.8), squeeze=False)
    for i, ax in enumerate(axes[0]):
        ax.plot(time, scores[:, :, i].T, lw=0.6, alpha=0.5, color="tab:blue")
        ax.set_title(f"PC {i + 1}", fontsize=10)
        ax.set_xlabel("t")
    if title:
        fig.suptitle(title, fontsize=10)
    return _save(fig, path, dpi)


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if hasattr(x, "detach") else np.asarray(x, dtype=float)


def _save(fig, path: str | Path, dpi: int = DPI) -> Path:
    fig.tight_layout()
    return save_whole(fig, path, dpi=dpi)


def save_whole(fig, path: str | Path, **savefig: object) -> Path:
    """Save `fig` as `path` whole or not at all: to a temporary beside it, renamed over
    `path` once written (a figure cut off by a signal or a full disk leaves the old file,
    or none, and no temporary); then close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        fig.savefig(tmp, **savefig)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
        plt.close(fig)
    return path
