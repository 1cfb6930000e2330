"""Step-size controllers: from one step's error ratio to the next step's size.

PI control (`PIController`): factor = safety · r^(−β₁/p) · r_prev^(β₂/p), clamped to [0.2, 10]
after an accepted step and to [0.2, 0.9] after a rejected one (so that a rejected step always
shrinks); r is the RMS error ratio of the step (accept when r ≤ 1) and r_prev that of the last
accepted step.

β₁ = 0.85 and β₂ = 0.25, p = the error estimate's order + 1 (5 for the 5(4) pairs).
OrdinaryDiffEq.jl's defaults for Tsit5 (β₁ = 0.7/p, β₂ = 0.4/p) settle near r ≈ 0.17 and so
take ~20% more steps than needed; these (diffrax's `PIDController` with icoeff 0.6 and
pcoeff 0.25) settle near r ≈ 0.4. On the coupled-Lorenz benchmark (rtol 1e-6) that is the
step count of an integral controller with 2.5× fewer rejected steps and 1.5× lower error
(docs/solver.md).

Integral control (`IController`) has no history term: factor = safety · r^(−1/p) (β₁ = 1),
torchode's and torchdiffeq's choice. The PI history term damps growth after very accurate
steps (r_prev ≪ 1 gives r_prev^β₂ < 1), which at loose tolerances on smooth solutions, where
steps are far from the error bound, costs steps for nothing: on MP-NODE training rollouts at
rtol = atol = 1e-4 the I controller takes 4 steps where PI takes 5 (docs/solver.md). `train`
therefore uses I and `generate` PI (`mpnode_cli.config`).

A controller owns the error test too (as diffrax's `PIDController(rtol, atol, ...)` and
torchode's `IntegralController(atol, rtol, ...)` do): its `rtol` and `atol` weigh each step's
error (`scale`), so `solve(..., controller=PIController(rtol=1e-8, atol=1e-10))` carries
them from the caller to the test in one object. Its exponents are given per order, as
diffrax's coefficients are: the solve divides them by p, the error estimate's order + 1.

`CONTROLLERS` maps the names that `solve(controller=...)` and `SolverOptions.controller`
accept to the classes, and the defaults of the tolerances are declared here once (`RTOL`,
`ATOL`; `solve` and `SolverOptions` take theirs from here). Controllers work on detached
`[B]` float64 tensors, one value per sample, in pure tensor code (no host sync), so the
solver's step can be compiled with them. This module imports no torch (it calls tensor
methods only), so that configs and the CLI's help can read it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

RTOL = 1e-6  # the default relative tolerance of `solve` and `SolverOptions`
ATOL = 1e-8  # the default absolute tolerance


@dataclass(frozen=True, kw_only=True)
class StepController:
    """What every controller has: the error test's tolerances, the bounds of a step-size
    change and a floor on r.

    Attributes:
        rtol, atol: per-element tolerances; a step is accepted when the RMS over the
            sample's elements of `err / (atol + rtol·max(|y|, |y_new|))` is at most 1.
        beta1: exponent of the current error ratio times p, r^(−β₁/p).
        safety: factor applied to every proposal; also the largest factor after a rejection.
        factor_min, factor_max: bounds of the step-size change after an accepted step.
        r_floor: keeps r^(−β₁/p) finite when a step is exact (e.g. a constant solution).
    """

    rtol: float = RTOL
    atol: float = ATOL
    beta1: float
    safety: float = 0.9
    factor_min: float = 0.2
    factor_max: float = 10.0
    r_floor: float = 1e-10

    name: ClassVar[str]

    def scale(self, y, y_new=None):
        """`[B, F]` the error's per-element weights atol + rtol·max(|y|, |y_new|) (|y|
        alone without `y_new`, as the first step size's heuristic takes them)."""
        scale = abs(y) if y_new is None else abs(y).maximum(abs(y_new))
        scale *= self.rtol
        scale += self.atol
        return scale

    def ratio(self, r, finite):
        """`[B]` error ratios made safe to exponentiate: inf where not finite, floored."""
        return r.where(finite, math.inf).clamp(self.r_floor)

    def initial_history(self) -> float:
        """The history's value before the first accepted step (each sample starts with it)."""
        return 1.0

    def propose(self, h, r, err_prev, accept, p: int):
        """The next step size and the updated history.

        Args:
            h: `[B]` the step just attempted; r: `[B]` its error ratio (from `ratio`);
            err_prev: `[B]` the history; accept: `[B]` bool, whether the step was accepted;
            p: the error estimate's order + 1 (5 for a 5(4) pair).

        Returns:
            `(dt_next [B], err_prev [B])`; a rejection leaves the history as it was.
        """
        raise NotImplementedError


@dataclass(frozen=True, kw_only=True)
class IController(StepController):
    """Integral control of the step size, per sample: factor = safety · r^(−β₁/p), β₁ = 1.

    It keeps no history: `propose` passes `err_prev` through unchanged.
    """

    beta1: float = 1.0

    name: ClassVar[str] = "i"

    def propose(self, h, r, err_prev, accept, p):
        q = self.safety * r.pow(-(self.beta1 / p))
        grow = q.clamp(self.factor_min, self.factor_max)
        shrink = q.clamp(self.factor_min, self.safety)
        return h * grow.where(accept, shrink), err_prev


@dataclass(frozen=True, kw_only=True)
class PIController(StepController):
    """PI control of the step size, per sample: factor = safety · r^(−β₁/p) · r_prev^(β₂/p).

    Attributes:
        beta2: exponent of the previous accepted step's error ratio r_prev, times p.
        err_prev_floor: the history never claims a better error than this (OrdinaryDiffEq.jl's
            `qoldinit`), also its value before the first accepted step.
    """

    beta1: float = 0.85
    beta2: float = 0.25
    err_prev_floor: float = 1e-4

    name: ClassVar[str] = "pi"

    def initial_history(self) -> float:
        return self.err_prev_floor

    def propose(self, h, r, err_prev, accept, p):
        q = r.pow(-(self.beta1 / p))
        grow = (self.safety * q * err_prev.pow(self.beta2 / p)).clamp(self.factor_min,
                                                                       self.factor_max)
        shrink = (self.safety * q).clamp(self.factor_min, self.safety)
        dt_next = h * grow.where(accept, shrink)
        return dt_next, r.clamp(self.err_prev_floor).where(accept, err_prev)


CONTROLLERS: dict[str, type[StepController]] = {c.name: c for c in (PIController, IController)}
CONTROLLER = "pi"  # the default of `solve` and `SolverOptions`


def controller_for(name: str, rtol: float = RTOL, atol: float = ATOL) -> StepController:
    """The controller `name` (a key of `CONTROLLERS`) with these tolerances and its own
    coefficients."""
    if name not in CONTROLLERS:
        raise ValueError(f"unknown step-size controller '{name}' "
                         f"(choose from: {', '.join(CONTROLLERS)})")
    return CONTROLLERS[name](rtol=rtol, atol=atol)
