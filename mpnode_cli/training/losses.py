"""Rollout losses, and the one state difference every loss and error measure takes.

Inputs are `[B, T, N, D]` normalized states; t₀ is excluded (it is given).
`node_mse_loss` weighs each node by its own scale, for graphs whose hubs' states are far
larger than a typical node's (`docs/transfer.md`). Where a run
wraps angles (`TrainConfig.wrap_angles` on a dataset that declares periodic states), the
difference of a periodic component is the wrapped one, atan2(sin Δ, cos Δ) ∈ (−π, π] of
the physical angles (an angle is only defined mod 2π); every other component's is plain.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch


@dataclass(frozen=True)
class Angles:
    """The state components whose differences are taken mod 2π.

    Attributes:
        dims: their indices among the D states.
        scale: `[D]` radians per unit of the states compared (the normalizer's `x_std` for
            normalized states), or None for physical states (radians).
    """

    dims: tuple[int, ...]
    scale: torch.Tensor | None = None

    def physical(self) -> Angles:
        """The same components, for states in physical units."""
        return Angles(self.dims)


def difference(pred: torch.Tensor, target: torch.Tensor,
               angles: Angles | None = None) -> torch.Tensor:
    """`pred − target` `[..., D]`; for the components of `angles`, the wrapped difference
    atan2(sin Δ, cos Δ) of the angles in radians, back in the states' units."""
    diff = pred - target
    if angles is None or not angles.dims:
        return diff
    index = torch.as_tensor(angles.dims, dtype=torch.long, device=diff.device)
    scale = (torch.ones((), dtype=diff.dtype, device=diff.device) if angles.scale is None
             else angles.scale.to(diff).index_select(0, index))
    radians = diff.index_select(-1, index) * scale
    wrapped = torch.atan2(torch.sin(radians), torch.cos(radians)) / scale
    return diff.index_copy(-1, index, wrapped)


def run_angles(wrap: bool, facts: Mapping[str, Any], x_std: torch.Tensor | None
               ) -> Angles | None:
    """The `Angles` of a run: the training dataset's periodic states (`facts`: a
    checkpoint's `dataset` record) when it wraps angles, else None (plain differences).

    Args:
        wrap: `TrainConfig.wrap_angles`.
        facts: `state_names` and `periodic_states` (absent: none).
        x_std: the normalizer's `[D]` std (the errors are taken in normalized units).
    """
    names: Sequence[str] = facts.get("state_names") or ()
    periodic = set(facts.get("periodic_states") or ())
    dims = tuple(i for i, name in enumerate(names) if name in periodic)
    if not wrap or not dims:
        return None
    return Angles(dims, None if x_std is None else x_std.detach().clone())


def huber_loss(pred: torch.Tensor, target: torch.Tensor, delta: float = 1.0,
               angles: Angles | None = None) -> torch.Tensor:
    """The authors' "Huber along time", `time_series_huber` (MPNODE.jl `src/losses.jl:56-62`).

    Huber(δ) per element, summed over time (t₁…t_T) and features, averaged over
    trajectories × nodes. `angles`: components compared mod 2π (`difference`).
    """
    err = difference(pred[:, 1:], target[:, 1:], angles).abs()  # (B, T-1, N, D)
    quad = torch.clamp(err, max=delta)
    per_elem = 0.5 * quad**2 + delta * (err - quad)
    return per_elem.sum(dim=(1, 3)).mean()


def mse_loss(pred: torch.Tensor, target: torch.Tensor,
             angles: Angles | None = None) -> torch.Tensor:
    """Mean squared error over every predicted element (t₁…t_T, nodes, features, batch).

    This is also the paper's "test error" when taken in normalized units. `angles`:
    components compared mod 2π (`difference`).
    """
    return difference(pred[:, 1:], target[:, 1:], angles).pow(2).mean()


# The least variance `node_mse_loss` divides by, in normalized units (a state std of 1):
# a node that moves less than 3% of the pooled std over the window counts as one that
# moves that much, so a node at rest does not weigh without bound.
NODE_VARIANCE_FLOOR = 1e-3


def node_mse_loss(pred: torch.Tensor, target: torch.Tensor,
                  angles: Angles | None = None) -> torch.Tensor:
    """Node-scaled MSE: each squared error divided by its node's own variance over the
    window, `target`'s variance along time per trajectory, node and feature (plus
    `NODE_VARIANCE_FLOOR`), then the mean over every predicted element.

    On a graph whose hubs' states are 100× a typical node's, the plain MSE is the hubs'
    error and the typical nodes are not fitted; this one is each node's error relative to
    how far it moves, so nodes on every scale count alike. `angles`: as `mse_loss`.
    """
    scale = target.var(dim=1, keepdim=True, correction=0) + NODE_VARIANCE_FLOOR
    return (difference(pred[:, 1:], target[:, 1:], angles).pow(2) / scale).mean()


LOSSES = {"huber": huber_loss, "mse": mse_loss, "node-mse": node_mse_loss}


def dataset_loss_scale(balance: bool, train_sets: Sequence, normalizer: Any
                       ) -> list[float] | None:
    """Each training dataset's factor on its loss under `--balance-datasets` (`balance`)
    with several datasets: 1 / the population variance of its train states as the run's
    `normalizer` maps them (over trajectories, samples, nodes and components); None
    otherwise (every value counts alike). Several datasets are always in memory."""
    if not balance or len(train_sets) < 2:
        return None
    variances = [float(normalizer.norm_x(t.states).to(torch.float64).var(correction=0))
                 for t in train_sets]
    return [1.0 / max(v, 1e-12) for v in variances]
