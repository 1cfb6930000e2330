"""Batched Runge–Kutta ODE solvers in torch: `solve(f, y0, t_eval, method=...) -> Solution`,
the step-size controllers (`PIController(rtol=..., atol=...)`) and `SolverOptions`.

Names are re-exported lazily, so that `mpnode_cli.solver.options`, `.controller` and
`.tableau` (which the configs and the CLI's help read) import without torch.
"""

from __future__ import annotations

from mpnode_cli.lazy import lazy_exports

__getattr__, __all__ = lazy_exports(__name__, {
    "solution": ["Solution", "Status"],
    "solve": ["solve"],
    "options": ["SolverOptions"],
    "controller": ["IController", "PIController", "StepController"],
    "tableau": ["ButcherTableau", "METHODS"],
}, globals())
