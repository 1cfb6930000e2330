"""Batched Runge–Kutta ODE solvers in torch: `solve(f, y0, t_eval, method=...) -> Solution`.

Names are re-exported lazily, so that `mpnode_cli.solver.options` and `.tableau` (which the
configs and the CLI's help read) import without torch.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_EXPORTS = {
    "Solution": "solution",
    "Status": "solution",
    "solve": "solve",
    "SolverOptions": "options",
    "ButcherTableau": "tableau",
    "METHODS": "tableau",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'mpnode_cli.solver' has no attribute '{name}'")
    module = import_module(f"mpnode_cli.solver.{_EXPORTS[name]}")
    # Importing the submodule `solve` binds the package's `solve` to that module; the
    # exports, bound here afterwards, take the name back for the function. (Code that
    # imports `mpnode_cli.solver.solve` as a module before anything asks the package for
    # `solve` would leave the module there: import the names from the package.)
    exports = {key: getattr(module, key) for key, where in _EXPORTS.items()
               if where == _EXPORTS[name]}
    globals().update(exports)
    return exports[name]
