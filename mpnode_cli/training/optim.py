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

    Attributes:
        param_groups: one group, `{"lr", "betas", "eps", "params"}` (as `torch.optim`).
        state: per parameter, `step` (float32 scalar tensor), `exp_avg`, `exp_avg_sq`.
    """

    def __init__(self, params: Iterable[torch.nn.Parameter], lr: float = 1e-3,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.params = [p for p in params if p.requires_grad]
        self.param_groups = [{"lr": lr, "betas": betas, "eps": eps, "weight_decay": 0,
                              "amsgrad": False, "maximize": False, "params": self.params}]
        self.state: dict[torch.nn.Parameter, dict[str, torch.Tensor]] = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            if set_to_none:
                p.grad = None
            elif p.grad is not None:
                p.grad.zero_()

    @torch.no_grad()
    def step(self) -> None:
        group = self.param_groups[0]
        lr, (beta1, beta2), eps = group["lr"], group["betas"], group["eps"]
        for p in self.params:
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
        group = {k: v for k, v in self.param_groups[0].items() if k != "params"}
        return {"state": {index[id(p)]: dict(s) for p, s in self.state.items()},
                "param_groups": [{**group, "params": list(range(len(self.params)))}]}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """Load a state written by this class or by `torch.optim.Adam`."""
        (group,) = state_dict["param_groups"]
        if len(group["params"]) != len(self.params):
            raise ValueError(f"optimizer state for {len(group['params'])} parameters, the "
                             f"model has {len(self.params)}")
        for key in ("lr", "betas", "eps"):
            value = group[key]
            self.param_groups[0][key] = tuple(value) if key == "betas" else value
        self.state = {}
        for i, s in state_dict["state"].items():
            p = self.params[group["params"].index(int(i))]
            self.state[p] = {"step": s["step"].detach().clone().cpu(),
                             "exp_avg": s["exp_avg"].detach().clone().to(p),
                             "exp_avg_sq": s["exp_avg_sq"].detach().clone().to(p)}
