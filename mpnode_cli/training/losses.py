"""Rollout losses. Inputs are `[B, T, N, D]` normalized states; t₀ is excluded (it is given)."""

from __future__ import annotations

import torch


def huber_loss(pred: torch.Tensor, target: torch.Tensor, delta: float = 1.0) -> torch.Tensor:
    """The authors' "Huber along time", `time_series_huber` (MPNODE.jl `src/losses.jl:56-62`).

    Huber(δ) per element, summed over time (t₁…t_T) and features, averaged over
    trajectories × nodes.
    """
    err = (pred[:, 1:] - target[:, 1:]).abs()  # (B, T-1, N, D)
    quad = torch.clamp(err, max=delta)
    per_elem = 0.5 * quad**2 + delta * (err - quad)
    return per_elem.sum(dim=(1, 3)).mean()


def mse_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error over every predicted element (t₁…t_T, nodes, features, batch).

    This is also the paper's "test error" when taken in normalized units.
    """
    return (pred[:, 1:] - target[:, 1:]).pow(2).mean()


LOSSES = {"huber": huber_loss, "mse": mse_loss}
