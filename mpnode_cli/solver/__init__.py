"""Batched Tsit5 ODE solver in torch: `solve(f, y0, t_eval, ...) -> Solution`."""

from mpnode_cli.solver.solve import Solution, Status, solve

__all__ = ["Solution", "Status", "solve"]
