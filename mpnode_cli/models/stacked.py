"""Layers that also take an ensemble's stacked weights, and the members a rollout runs.

An ensemble (`mpnode_cli.models.ensemble`) rolls its S members out in one solve: their
parameters are stacked (`[S, ...]`) and swapped into one member for the call
(`torch.func.functional_call`, as in PyTorch's `torch.func.stack_module_state` recipe,
https://pytorch.org/docs/stable/func.api.html). The models' `Linear` and `LayerNorm` are
these: with an ordinary weight they are torch's; with a stacked one (`weight.dim()` one
more than torch's) the input's leading rows are member-major (member k's rows k·R …
(k+1)·R − 1 of S·R), so `x.reshape(S, R, in)` lines each member's rows up with its
weight, and the layer applies each member's weights to its rows as one batched matmul
(`linear`). The layers read nothing but their weights: S is the weights' leading size.
Everything else a model does acts row by row already.

The rollout is told its members explicitly (`StackedMembers`). A solve that goes on with
some members' rows only (compaction, `NeuralODEModel.rollout`) re-binds the kept members'
weights (`StackedMembers.kept`): each stacked parameter `index_select`ed along its member
axis and swapped in with `functional_call` for the call, so nothing is shared or mutated.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.func import functional_call


class _Apply(nn.Module):
    """`forward(fn, *args)` is `fn(*args)`: runs a function of `model`'s under
    `functional_call`, whose parameter names are `model.`-prefixed."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, fn: Callable, *args):
        return fn(*args)


@dataclass(frozen=True)
class StackedMembers:
    """The S members a stacked rollout runs: their parameters, each stacked `[S, ...]`.

    The rollout's rows are member-major (member k's are rows k·R … (k+1)·R − 1 of S·R).

    Attributes:
        weights: by one member's parameter name, the members' values stacked along a new
            leading axis (differentiable, so gradients reach each member's own tensors).
    """

    weights: Mapping[str, torch.Tensor]

    @property
    def size(self) -> int:
        """S, the members stacked."""
        return next(iter(self.weights.values())).shape[0]

    def kept(self, model: nn.Module, members: torch.Tensor, f: Callable) -> Callable:
        """`f` (a function of `model`'s, e.g. its vector field), called with the weights of
        `members` (`[K]` int64, sorted) only: its input's rows are those members' rows,
        member after member."""
        call = _Apply(model)

        def kept(*args):
            weights = {"model." + name: w.index_select(0, members)
                       for name, w in self.weights.items()}
            return functional_call(call, weights, (f, *args))

        return kept


def stacked_linear(x: torch.Tensor, weight: torch.Tensor,
                   bias: torch.Tensor | None) -> torch.Tensor:
    """`x: [S·R..., in]`, `weight: [S, out, in]`, `bias: [S, out]` → `[S·R..., out]`."""
    s = weight.shape[0]
    rows = x.reshape(s, -1, x.shape[-1])  # (S, R, in)
    if bias is None:
        y = torch.bmm(rows, weight.transpose(1, 2))
    else:
        y = torch.baddbmm(bias.unsqueeze(1), rows, weight.transpose(1, 2))  # (S, R, out)
    return y.reshape(*x.shape[:-1], weight.shape[1])


def stacked_layer_norm(x: torch.Tensor, shape, weight: torch.Tensor,
                       bias: torch.Tensor | None, eps: float) -> torch.Tensor:
    """`F.layer_norm` over the last dim with a `[S, H]` weight and bias."""
    normed = F.layer_norm(x, shape, None, None, eps)
    s = weight.shape[0]
    rows = normed.reshape(s, -1, normed.shape[-1])  # (S, R, H)
    out = rows * weight.unsqueeze(1) + (bias.unsqueeze(1) if bias is not None else 0)
    return out.reshape(normed.shape)


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """`F.linear`, which also takes stacked `[S, out, in]` weights (module docstring)."""
    if weight.dim() == 3:
        return stacked_linear(x, weight, bias)
    return F.linear(x, weight, bias)


class Linear(nn.Linear):
    """`nn.Linear`, which also takes stacked `[S, out, in]` weights (module docstring)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return linear(x, self.weight, self.bias)


class LayerNorm(nn.LayerNorm):
    """`nn.LayerNorm` over the last dim, which also takes stacked `[S, H]` weights."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight is not None and self.weight.dim() == 2:
            return stacked_layer_norm(x, self.normalized_shape, self.weight, self.bias,
                                      self.eps)
        return super().forward(x)
