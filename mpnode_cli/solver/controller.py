"""Step-size controllers: from one step's error ratio to the next step's size.

PI control (`PIController`): factor = safety · r^(−β₁) · r_prev^(β₂), clamped to [0.2, 10]
after an accepted step and to [0.2, 0.9] after a rejected one (so that a rejected step always
shrinks); r is the RMS error ratio of the step (accept when r ≤ 1) and r_prev that of the last
accepted step.

β₁ = 0.85/p and β₂ = 0.25/p, p = the error estimate's order + 1 (5 for the 5(4) pairs).
OrdinaryDiffEq.jl's defaults for Tsit5 (β₁ = 0.7/p, β₂ = 0.4/p) settle near r ≈ 0.17 and so
take ~20% more steps than needed; these (diffrax's `PIDController` with icoeff 0.6 and
pcoeff 0.25) settle near r ≈ 0.4. On the coupled-Lorenz benchmark (rtol 1e-6) that is the
step count of an integral controller with 2.5× fewer rejected steps and 1.5× lower error
(docs/solver.md).

Integral control (`IController`) has no history term: factor = safety · r^(−1/p),
torchode's and torchdiffeq's choice. The PI history term damps growth after very accurate
steps (r_prev ≪ 1 gives r_prev^β₂ < 1), which at loose tolerances on smooth solutions, where
steps are far from the error bound, costs steps for nothing: on MP-NODE training rollouts at
rtol = atol = 1e-4 the I controller takes 4 steps where PI takes 5 (docs/solver.md). `train`
therefore uses I and `generate` PI (`mpnode_cli.config`).

`CONTROLLERS` maps the names that `solve(controller=...)` and `SolverOptions.controller`
accept to the classes. Controllers work on detached `[B]` float64 arrays, one value per
sample, through the solve's array namespace (`host.py`): numpy views of the tensors on the
CPU, or the tensors themselves in pure tensor code (no host sync), so the solver's step can
be compiled with them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from mpnode_cli.solver.host import Ops, TorchOps


@dataclass(frozen=True, kw_only=True)
class StepController:
    """What every controller has: the bounds of a step-size change and a floor on r.

    Attributes:
        beta1: exponent of the current error ratio, r^(−β₁).
        safety: factor applied to every proposal; also the largest factor after a rejection.
        factor_min, factor_max: bounds of the step-size change after an accepted step.
        r_floor: keeps r^(−β₁) finite when a step is exact (e.g. a constant solution).
    """

    beta1: float
    safety: float = 0.9
    factor_min: float = 0.2
    factor_max: float = 10.0
    r_floor: float = 1e-10

    name: ClassVar[str]

    @classmethod
    def for_order(cls, p: int) -> StepController:
        """The controller for an error estimate of order p − 1."""
        raise NotImplementedError

    def ratio(self, r, finite, xp: Ops = TorchOps):
        """`[B]` error ratios made safe to exponentiate: inf where not finite, floored.
        `xp` is the namespace of the arrays (`host.py`)."""
        return xp.clip(xp.where(finite, r, math.inf), self.r_floor)

    def initial_history(self) -> float:
        """The history's value before the first accepted step (each sample starts with it)."""
        return 1.0

    def propose(self, h, r, err_prev, accept, xp: Ops = TorchOps):
        """The next step size and the updated history.

        Args:
            h: `[B]` the step just attempted; r: `[B]` its error ratio (from `ratio`);
            err_prev: `[B]` the history; accept: `[B]` bool, whether the step was accepted;
            xp: their namespace (`host.py`).

        Returns:
            `(dt_next [B], err_prev [B])`; a rejection leaves the history as it was.
        """
        raise NotImplementedError


@dataclass(frozen=True, kw_only=True)
class IController(StepController):
    """Integral control of the step size, per sample: factor = safety · r^(−β₁), β₁ = 1/p.

    It keeps no history: `propose` passes `err_prev` through unchanged.
    """

    name: ClassVar[str] = "i"

    @classmethod
    def for_order(cls, p: int) -> IController:
        return cls(beta1=1.0 / p)

    def propose(self, h, r, err_prev, accept, xp=TorchOps):
        q = self.safety * xp.pow(r, -self.beta1)
        grow = xp.clip(q, self.factor_min, self.factor_max)
        shrink = xp.clip(q, self.factor_min, self.safety)
        return h * xp.where(accept, grow, shrink), err_prev


@dataclass(frozen=True, kw_only=True)
class PIController(StepController):
    """PI control of the step size, per sample: factor = safety · r^(−β₁) · r_prev^(β₂).

    Attributes:
        beta2: exponent of the previous accepted step's error ratio r_prev.
        err_prev_floor: the history never claims a better error than this (OrdinaryDiffEq.jl's
            `qoldinit`), also its value before the first accepted step.
    """

    beta2: float
    err_prev_floor: float = 1e-4

    name: ClassVar[str] = "pi"

    @classmethod
    def for_order(cls, p: int) -> PIController:
        return cls(beta1=0.85 / p, beta2=0.25 / p)

    def initial_history(self) -> float:
        return self.err_prev_floor

    def propose(self, h, r, err_prev, accept, xp=TorchOps):
        q = xp.pow(r, -self.beta1)
        grow = xp.clip(self.safety * q * xp.pow(err_prev, self.beta2), self.factor_min,
                       self.factor_max)
        shrink = xp.clip(self.safety * q, self.factor_min, self.safety)
        dt_next = h * xp.where(accept, grow, shrink)
        return dt_next, xp.where(accept, xp.clip(r, self.err_prev_floor), err_prev)


CONTROLLERS: dict[str, type[StepController]] = {c.name: c for c in (PIController, IController)}


def controller_for(name: str, p: int) -> StepController:
    """The controller `name` (a key of `CONTROLLERS`) for an error estimate of order p − 1."""
    if name not in CONTROLLERS:
        raise ValueError(f"unknown step-size controller '{name}' "
                         f"(choose from: {', '.join(CONTROLLERS)})")
    return CONTROLLERS[name].for_order(p)
