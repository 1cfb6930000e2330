"""The two naive predictors every error is shown beside: hold x(0) and the train split's
time mean, as one MSE each (`baseline_mse`, evaluate's tables) and as MSE against time
(`baseline_mse_vs_time`, evaluate's error plot), measured as `EvalResult` measures the
model: normalized units, t₀ excluded from the mean."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories, in_blocks
from mpnode_cli.training.losses import Angles, difference

BASELINES = ("hold_x0", "time_mean")


def baseline_mse(train: TrajectoryData | StreamedTrajectories | Sequence[TrajectoryData],
                 data: TrajectoryData | StreamedTrajectories,
                 normalizer: Normalizer, angles: Angles | None = None) -> dict[str, float]:
    """The MSE of two naive predictors on `data`, in `evaluate`'s units.

    Both are measured as `EvalResult.mse` is: normalized units, t₀ excluded, the mean over
    every predicted sample, node and feature (over all trajectories of `data`, including any
    whose model rollout failed).

    - hold_x0: x̂(t_k) = x(t₀), every node keeps its initial state.
    - time_mean: x̂(t_k) = the mean of the train trajectories' states at t_k, over
      trajectories and nodes, per feature. A sample time of `data` takes the train mean of
      the latest train sample time at or before it, so equal grids match sample by sample
      and beyond the train horizon the last train time-mean is held.

    Args: as `baseline_mse_vs_time`.

    Returns:
        `{"hold_x0": float, "time_mean": float}`, NaN where undefined (empty `data` or
        `train`, or a single sample time).
    """
    return mean_of_curves(baseline_mse_vs_time(train, data, normalizer, angles))


def mean_of_curves(curves: dict[str, np.ndarray]) -> dict[str, float]:
    """`baseline_mse` from `baseline_mse_vs_time`'s curves: each one's mean over t₁.. (every
    sample time holds as many values, so this is the mean over all predicted values)."""
    return {name: float(curve[1:].mean()) if len(curve) > 1 else math.nan
            for name, curve in curves.items()}


def baseline_mse_vs_time(train: TrajectoryData | StreamedTrajectories | Sequence[TrajectoryData],
                         data: TrajectoryData | StreamedTrajectories, normalizer: Normalizer,
                         angles: Angles | None = None) -> dict[str, np.ndarray]:
    """The two naive predictors' MSE at each sample time of `data` (`baseline_mse`'s).

    Args:
        train: trajectories whose per-time mean is the time_mean predictor (the split the
            model was trained on), or a list of several datasets' (pooled: at each sample
            time, the mean over the trajectories and nodes of those that have it).
        data: the trajectories to score; physical units both, in memory or streamed
            (then read a block of trajectories at a time).
        normalizer: the training normalization.
        angles: state components compared mod 2π, as `evaluate` takes them.

    Returns:
        `{"hold_x0": [T], "time_mean": [T]}` float64, each the mean over trajectories,
        nodes and features at t_k (0 at t₀ for hold_x0); all NaN where undefined (empty
        `data`, or time_mean without `train`).
    """
    t = data.time.numel()
    nan = np.full(t, math.nan)
    if len(data) == 0:
        return {"hold_x0": nan, "time_mean": nan.copy()}
    pred = time_mean_prediction(train, data.time, normalizer)  # (T, D) or None
    hold = torch.zeros(t, dtype=torch.float64)
    time_mean = torch.zeros(t, dtype=torch.float64)
    count = 0
    for block in in_blocks(data):
        x = normalizer.norm_x(block.states.double())  # (B, T, N, D)
        hold += difference(x, x[:, :1], angles).pow(2).sum(dim=(0, 2, 3))
        if pred is not None:
            time_mean += difference(x, pred[None, :, None, :], angles).pow(2).sum(dim=(0, 2, 3))
        count += x[:, 0].numel()  # values per sample time
    return {"hold_x0": (hold / count).numpy(),
            "time_mean": (time_mean / count).numpy() if pred is not None else nan}


def time_mean_prediction(train: TrajectoryData | StreamedTrajectories
                         | Sequence[TrajectoryData], time: torch.Tensor,
                         normalizer: Normalizer) -> torch.Tensor | None:
    """The time_mean predictor at the sample times `time` (`[T]`): `[T, D]` float64 in
    `normalizer`'s units (`baseline_mse` says which train time each takes), or None
    without train trajectories. `train` as `baseline_mse_vs_time` takes it."""
    if not isinstance(train, TrajectoryData | StreamedTrajectories):
        train, mean_t = _pooled_time_mean(train, normalizer)
    elif len(train):
        total = sum(normalizer.norm_x(block.states.double()).sum(dim=(0, 2))
                    for block in in_blocks(train))
        mean_t = total / (len(train) * train.num_nodes)  # (T', D)
    if not len(train):
        return None
    # Sample grids come from float arithmetic: a tolerance keeps t_k = 0.3 on 0.30000000004.
    ts, train_ts = time.double(), train.time.double()
    slack = 1e-9 * max(1.0, float(ts.abs().max()))
    at = torch.searchsorted(train_ts, ts + slack, right=True) - 1  # (T,) latest t' ≤ t_k
    return mean_t[at.clamp(0, len(train_ts) - 1)]  # (T, D)


def _pooled_time_mean(train: Sequence[TrajectoryData], normalizer: Normalizer
                      ) -> tuple[TrajectoryData, torch.Tensor]:
    """The longest of several train splits (its grid holds every other's sample times,
    `mpnode_cli.data.pooled.check_poolable`) and the pooled normalized time mean on it,
    `[T', D]`: at t_k, over the trajectories and nodes of the splits that have t_k."""
    longest = max(train, key=lambda d: d.time.numel())
    t, d = longest.time.numel(), longest.node_dim
    total = torch.zeros(t, d, dtype=torch.float64)
    count = torch.zeros(t, 1, dtype=torch.float64)
    for part in train:
        k = part.time.numel()
        total[:k] += normalizer.norm_x(part.states.double()).sum(dim=(0, 2))  # (T_j, D)
        count[:k] += len(part) * part.num_nodes
    return longest, total / count.clamp(min=1)
