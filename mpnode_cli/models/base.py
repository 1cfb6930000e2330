"""What every model shares: the rollout result and the MLP builder."""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
from torch import nn

ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "relu": nn.ReLU,
    "elu": nn.ELU,
    "silu": nn.SiLU,
    "softplus": nn.Softplus,
}


@dataclass
class Rollout:
    """Predicted trajectories.

    Attributes:
        states: `[B, T, N, D]` predicted (normalized) node states; index 0 is x0.
        messages: `[B, T, N, M]` message states, when asked for and the model has them.
        status: `[B]` int64 `mpnode_cli.solver.Status` per trajectory (all 0 for models
            that do not use the ODE solver).
        n_f_evals: vector-field evaluations (max over the batch; 0 without a solver).
    """

    states: torch.Tensor
    messages: torch.Tensor | None
    status: torch.Tensor
    n_f_evals: int


def mlp(in_dim: int, hidden: int, layers: int, out_dim: int, activation: str) -> nn.Sequential:
    """`layers` hidden layers of width `hidden` with `activation`, then a linear output.

    Weights are Glorot-uniform and biases zero, as Flux's `Dense` (the authors' init).
    """
    if activation not in ACTIVATIONS:
        raise ValueError(f"unknown activation '{activation}' (choose from: "
                         f"{', '.join(ACTIVATIONS)})")
    if layers < 1 or hidden < 1:
        raise ValueError("an MLP needs at least one hidden layer of width ≥ 1")
    dims = [in_dim] + [hidden] * layers
    modules: list[nn.Module] = []
    for a, b in itertools.pairwise(dims):
        modules += [nn.Linear(a, b), ACTIVATIONS[activation]()]
    modules.append(nn.Linear(dims[-1], out_dim))
    for module in modules:
        if isinstance(module, nn.Linear):
            nn.init.xavier_uniform_(module.weight)
            nn.init.zeros_(module.bias)
    return nn.Sequential(*modules)


def zoh_controls(controls: torch.Tensor, ts: torch.Tensor):
    """u(t) for a zero-order hold: `controls[:, k]` acts on `[ts[k], ts[k+1])`.

    Args:
        controls: `[B, T, N, U]`; ts: `[T]` float64.

    Returns:
        `u(t: [B]) -> [B, N, U]`.
    """
    rows = torch.arange(controls.shape[0], device=controls.device)
    last = ts.numel() - 2  # the last sample's control is never held over an interval

    def u(t: torch.Tensor) -> torch.Tensor:
        k = (torch.searchsorted(ts, t.contiguous(), right=True) - 1).clamp(0, max(last, 0))
        return controls[rows, k]

    return u


def rollout_from_data(model, x: torch.Tensor, ts: torch.Tensor, adjacency: torch.Tensor,
                      controls: torch.Tensor | None = None, **options) -> Rollout:
    """Roll `model` out from the start of the data trajectories `x: [B, T, N, D]`.

    Every model starts from x(t₀); one with an input history of C > 1 states (L2S
    `history`) is given the data's first C states.
    """
    history = getattr(model, "history", 1)
    extra = {"history": x[:, :history]} if history > 1 else {}
    return model.rollout(x[:, 0], ts, adjacency, controls, **options, **extra)
