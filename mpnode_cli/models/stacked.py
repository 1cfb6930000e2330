"""Layers that also take an ensemble's stacked weights, and the context that says which.

An ensemble (`mpnode_cli.models.ensemble`) rolls its S members out in one solve: their
parameters are stacked (`[S, ...]`) and swapped into one member for the call
(`torch.func.functional_call`). The models' `Linear` and `LayerNorm` are these: with an
ordinary weight they are torch's; with a stacked one (`weight.dim()` one more than
torch's) the input's leading rows are member-major (member k's rows k·R … (k+1)·R − 1 of
S·R), so `x.reshape(S, R, in)` lines each member's rows up with its weight, and the layer
applies each member's weights to its rows as one batched matmul (`linear` does the same
for a weight that is a model's own parameter, as an MLP's linear path). Everything else a
model does acts row by row already.

A solve that goes on with some members' rows only (compaction, `NeuralODEModel.rollout`)
calls its right-hand side under `StackedLayers.keep`, and the layers then take those
members' weights.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import contextmanager
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import nn


class StackedLayers:
    """The ensemble rollout in progress: how many members are stacked, and which of them
    still run.

    Args:
        size: S, the members stacked (the weights' leading axis).
    """

    _current: ClassVar[list[StackedLayers]] = []

    def __init__(self, size: int):
        self.size = size
        self.members: torch.Tensor | None = None  # `[K]` the members whose rows run

    @staticmethod
    def current() -> StackedLayers | None:
        """The ensemble rollout in progress (`made_current`), or None."""
        return StackedLayers._current[-1] if StackedLayers._current else None

    @contextmanager
    def made_current(self):
        """Within the block, `current()` is this one."""
        StackedLayers._current.append(self)
        try:
            yield self
        finally:
            StackedLayers._current.pop()

    def keep(self, members: torch.Tensor, f: Callable) -> Callable:
        """`f`, called with the weights of `members` (`[K]` int64, sorted) only: its input's
        rows are those members' rows, member after member."""
        def kept(*args):
            outer, self.members = self.members, members
            try:
                return f(*args)
            finally:
                self.members = outer

        return kept


def _kept(param: torch.Tensor | None) -> torch.Tensor | None:
    """A stacked parameter's running members (differentiable), all of them outside `keep`."""
    context = StackedLayers.current()
    if param is None or context is None or context.members is None:
        return param
    return param.index_select(0, context.members)


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
        return stacked_linear(x, _kept(weight), _kept(bias))
    return F.linear(x, weight, bias)


class Linear(nn.Linear):
    """`nn.Linear`, which also takes stacked `[S, out, in]` weights (module docstring)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return linear(x, self.weight, self.bias)


class LayerNorm(nn.LayerNorm):
    """`nn.LayerNorm` over the last dim, which also takes stacked `[S, H]` weights."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.weight is not None and self.weight.dim() == 2:
            return stacked_layer_norm(x, self.normalized_shape, _kept(self.weight),
                                      _kept(self.bias), self.eps)
        return super().forward(x)
