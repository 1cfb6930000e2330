"""`SolverOptions`: how a verb asks the solver to integrate, as one typed value.

The generate and train configs each hold one as their `solver` field (with their own
defaults, `mpnode_cli.config`), and the layers between pass it on unchanged until
`solve(f, y0, t_eval, **options.solve_kwargs())`, which builds the step-size controller
from `controller`, `rtol` and `atol`, and gives a compiled solve the options' own
`CompileCache`. The field defaults are declared once: the method's and
`max_steps`' here (`solve` takes them from here), the tolerances' and the controller's in
`controller.py`. Torch-free, like `tableau` and `controller`, so that configs and the CLI's
help can be built without importing torch.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, model_validator

from mpnode_cli.limits import EPS, RTOL_ULPS
from mpnode_cli.solver.compile_cache import CompileCache
from mpnode_cli.solver.controller import ATOL, CONTROLLER, CONTROLLERS, RTOL, controller_for
from mpnode_cli.solver.tableau import METHODS, get_method

Method = Literal[tuple(METHODS)]  # the registered methods' names
Controller = Literal[tuple(CONTROLLERS)]  # the registered controllers' names
METHOD = "tsit5"  # the default method of `solve` and `SolverOptions`
MAX_STEPS = 100_000  # the default attempted steps per sample

_METHOD_HELP = "Runge–Kutta method: " + ", ".join(
    f"{name} ({tableau.summary})" for name, tableau in METHODS.items()) + "."


class SolverOptions(BaseModel):
    """Options of `mpnode_cli.solver.solve` that a config carries.

    Attributes:
        method: a name of `mpnode_cli.solver.tableau.METHODS`.
        rtol, atol: per-element tolerances of adaptive steps (the controller's).
        fixed_dt: take fixed steps of at most this size instead (no error control).
        max_steps: attempted steps per sample before it is marked `MAX_STEPS`.
        compile: run the adaptive step through `torch.compile`; "auto" lets the verb decide
            (training compiles long runs: `mpnode_cli.training.recipe.resolve_compile`), and
            stands for False where nothing decides.
        controller: adaptive step-size control, "pi" or "i" (a name of
            `controller.CONTROLLERS`; `solve_kwargs` builds the typed controller, with
            `rtol` and `atol`).
        compact: once most samples have finished, go on with the running ones only (where
            the caller can restrict its right-hand side to them: the neural ODEs' rollouts);
            the same result up to rounding, fewer rows stepped.
        checkpoints: backpropagate keeping at most this many solver states, the steps
            recomputed from them (`mpnode_cli.solver.checkpoint`): memory that does not
            grow with the steps, the same gradient, 1.5–2× the time; None: keep every step.

    Besides the fields, the options keep the compiled step of the solves run with them (and
    with their `model_copy`s): made on the first compiled solve, it is shared by the later
    ones, which reuse its graphs and, after a failed compile, its eager fallback. It is no
    part of their value: not stored, not compared, empty in a deep copy or a pickle.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    method: Method = Field(METHOD, description=_METHOD_HELP)
    rtol: float = Field(RTOL, gt=0, lt=1, description="Solver relative tolerance.")
    atol: float = Field(ATOL, gt=0, description="Solver absolute tolerance.")
    fixed_dt: float | None = Field(
        None, gt=0, description="Fixed steps of at most this size instead of adaptive ones.")
    max_steps: int = Field(MAX_STEPS, ge=1, description="Attempted steps per trajectory.")
    compile: bool | Literal["auto"] = Field(
        False, description="torch.compile the adaptive step (auto: training decides by the "
        "run's length).")
    controller: Controller = Field(
        CONTROLLER, description="Adaptive step-size control: pi (proportional-integral) or i "
        "(integral; fewer steps at loose tolerances).")
    compact: bool = Field(
        True, description="Once most trajectories have finished, step the running ones only "
        "(adaptive, uncompiled steps).")
    checkpoints: int | None = Field(
        None, ge=1, description="Backpropagate through the solve keeping at most this many "
        "solver states, recomputing the steps between (none: keep every step).")
    _compiled: CompileCache = PrivateAttr(default_factory=CompileCache)

    @model_validator(mode="after")
    def _check_method(self) -> SolverOptions:
        get_method(self.method, self.fixed_dt)  # a method without error estimate: fixed_dt
        return self

    def check_precision(self, dtype: str) -> None:
        """Refuse an rtol below what adaptive steps in `dtype` can meet (`RTOL_ULPS` of its
        machine epsilon, `mpnode_cli.limits`): their error estimate would be rounding
        noise, and the steps would shrink towards `max_steps`.

        Raises:
            ValueError: one line, with the least rtol the dtype allows.
        """
        least = RTOL_ULPS * EPS[dtype]
        if self.fixed_dt is None and self.rtol < least:
            raise ValueError(f"rtol {self.rtol:g} is below what {dtype} can resolve: give at "
                             f"least {least:.2g} ({RTOL_ULPS} × its machine epsilon)")

    def solve_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of `solve` these options stand for: the controller built
        from its name and the tolerances; `compile`, the options' own cache or False
        ("auto": False)."""
        kwargs = self.model_dump(exclude={"rtol", "atol"})
        return kwargs | {"compile": self._compiled if self.compile is True else False,
                         "controller": controller_for(self.controller, self.rtol, self.atol)}
