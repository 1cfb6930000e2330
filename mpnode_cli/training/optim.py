"""Adam (Kingma & Ba 2015) without `torch.optim`.

`torch.optim.Optimizer` wraps `step`, `zero_grad` and `(load_)state_dict` in
`torch._disable_dynamo`, and the first call imports `torch._dynamo`: about 2 s on a quiet
core and 6 s on a busy one, paid by every `mpnode train` process before its first epoch.
This class does the same arithmetic as `torch.optim.Adam`'s single-tensor path (the one torch
uses for CPU tensors; no weight decay, no AMSGrad) and keeps its `state_dict` layout, so the
weights after each step are bit-identical (tested) and checkpoints written with either
resume with the other.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch


class Adam:
    """Adam with torch's defaults: betas (0.9, 0.999), eps 1e-8.

    Args:
        params: the parameters, in one group; or a list of groups, each a dict with its
            `params` (an ensemble: one group per member, each with its own lr).
        lr, betas, eps: every group's, at the start.

    Attributes:
        param_groups: `{"lr", "betas", "eps", "params"}` per group (as `torch.optim`).
        state: per parameter, `step` (float32 scalar tensor), `exp_avg`, `exp_avg_sq`.
    """

    def __init__(self, params: Iterable[torch.nn.Parameter] | list[dict[str, Any]],
                 lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):
        params = list(params)
        groups = params if params and isinstance(params[0], dict) else [{"params": params}]
        self.param_groups = [{"lr": lr, "betas": betas, "eps": eps, "weight_decay": 0,
                              "amsgrad": False, "maximize": False,
                              "params": [p for p in g["params"] if p.requires_grad]}
                             for g in groups]
        self.params = [p for g in self.param_groups for p in g["params"]]
        self.state: dict[torch.nn.Parameter, dict[str, torch.Tensor]] = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            if set_to_none:
                p.grad = None
            elif p.grad is not None:
                p.grad.zero_()

    @torch.no_grad()
    def step(self) -> None:
        """One update of every parameter that has a gradient (None: left as it is)."""
        for group in self.param_groups:
            self._step_group(group)

    def _step_group(self, group: dict[str, Any]) -> None:
        lr, (beta1, beta2), eps = group["lr"], group["betas"], group["eps"]
        for p in group["params"]:
            if p.grad is None:
                continue
            state = self.state.get(p)
            if state is None:
                # torch keeps the step on the CPU in the default float dtype.
                state = self.state[p] = {
                    "step": torch.tensor(0.0, dtype=torch.get_default_dtype()),
                    "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                    "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
            grad, exp_avg, exp_avg_sq = p.grad, state["exp_avg"], state["exp_avg_sq"]
            state["step"] += 1
            step = float(state["step"])
            exp_avg.lerp_(grad, 1 - beta1)
            exp_avg_sq.mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
            step_size = lr / (1 - beta1**step)
            denom = (exp_avg_sq.sqrt() / (1 - beta2**step) ** 0.5).add_(eps)
            p.addcdiv_(exp_avg, denom, value=-step_size)

    def state_dict(self) -> dict[str, Any]:
        """`torch.optim.Adam.state_dict()`'s layout: parameters by their index."""
        index = {id(p): i for i, p in enumerate(self.params)}
        groups = [{**{k: v for k, v in g.items() if k != "params"},
                   "params": [index[id(p)] for p in g["params"]]} for g in self.param_groups]
        return {"state": {index[id(p)]: dict(s) for p, s in self.state.items()},
                "param_groups": groups}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Load a state written by this class or by `torch.optim.Adam` (the same groups)."""
        groups = state_dict["param_groups"]
        if len(groups) != len(self.param_groups):
            raise ValueError(f"optimizer state of {len(groups)} parameter groups, the model "
                             f"has {len(self.param_groups)}")
        order = [i for g in groups for i in g["params"]]
        if len(order) != len(self.params):
            raise ValueError(f"optimizer state for {len(order)} parameters, the model "
                             f"has {len(self.params)}")
        for mine, group in zip(self.param_groups, groups, strict=True):
            for key in ("lr", "betas", "eps"):
                mine[key] = tuple(group[key]) if key == "betas" else group[key]
        self.state = {}
        for i, s in state_dict["state"].items():
            p = self.params[order.index(int(i))]
            self.state[p] = {"step": s["step"].detach().clone().cpu(),
                             "exp_avg": s["exp_avg"].detach().clone().to(p),
                             "exp_avg_sq": s["exp_avg_sq"].detach().clone().to(p)}

    def load_group_state(self, state_dict: dict[str, Any], g: int) -> None:
        """Restore parameter group g alone (its lr and its parameters' moments) from a
        `state_dict` of this optimizer: an ensemble member's rollback."""
        group, saved = self.param_groups[g], state_dict["param_groups"][g]
        group["lr"] = saved["lr"]
        index = {id(p): i for i, p in enumerate(self.params)}
        for p in group["params"]:
            s = state_dict["state"].get(index[id(p)])
            if s is None:
                self.state.pop(p, None)
                continue
            self.state[p] = {"step": s["step"].detach().clone().cpu(),
                             "exp_avg": s["exp_avg"].detach().clone().to(p),
                             "exp_avg_sq": s["exp_avg_sq"].detach().clone().to(p)}
