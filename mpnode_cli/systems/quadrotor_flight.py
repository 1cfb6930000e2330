"""A batch of quadrotor-swarm flights: plan, fly closed-loop, check.

`plan_reference` turns a flight's random draws into a collision-free `Reference`; `fly` runs
the digital controller every `CONTROL_DT` with the rotor forces held in between, integrates
the physics with our Tsit5 over each hold (so no step crosses a control update), samples the
dataset at the output times and checks every control update (`clearances`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

from mpnode_cli.solver import Status, solve
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.systems.base import Simulation
from mpnode_cli.systems.quadrotor_control import (
    CONTROL_DT,
    Controller,
    Reference,
    circle_directions,
    formation,
    hover_state,
)
from mpnode_cli.systems.quadrotor_dynamics import (
    QuadParams,
    cable_tensions,
    rotor_wrench,
    split_state,
    swarm_rhs,
)

# The doorway (RA-L `door_obstacles(r_cylinder=0.5, x_door=3.0)`): infinite vertical cylinders.
CYLINDERS = ((2.5, 1.0), (2.5, -1.0), (3.0, 1.0), (3.0, -1.0))
CYLINDER_RADIUS = 0.5
CEILING = 2.1  # the authors' bound on z, with the floor z ≥ 0
QUAD_RADIUS = 0.275  # the authors' quad radius
LOAD_RADIUS = 0.2
# Rejection thresholds.
MAX_CABLE_ERROR = 0.01  # m
GOAL_TOLERANCE = 0.3  # m
MAX_SATURATION = 0.05  # fraction of control updates with any rotor saturated
# Clearance the planned flight keeps beyond the checks, for tracking errors.
PLAN_MARGIN = 0.1  # m
# Peak acceleration (m/s²) of a quad's motion relative to the load while the formation changes.
FORMATION_ACCEL = 2.5
PLAN_DT = 0.05  # s between the planner's checks of a reference
PLAN_STEP = 0.1  # s a move or an unfold is delayed per planning round
PLAN_ROUNDS = 40
# Shortest horizon a flight fits in (the load crosses 6 m while the formation folds and opens).
MIN_HORIZON = 8.0  # s


def plan_reference(inputs: dict[str, torch.Tensor], horizon: float, n: int, cable: float
                   ) -> Reference:
    """The reference of each flight, timed so that it clears the doorway by `PLAN_MARGIN`.

    Timing, from the uniform draws u₀..u₇ (seconds for a 10 s horizon, scaled with it). Each
    formation blend lasts (1 + 0.25·u)·√(5.77·L/A), where L is the longest way a quad travels
    in it and A = `FORMATION_ACCEL`: a minimum-jerk move over L in time T peaks at 5.77·L/T²,
    so no quad's acceleration relative to the load exceeds about A. The fold starts at
    0.3·u₀ (polar blend u₁ then turning u₂ for even N; both together, the longer of the two,
    for odd N, see `Reference`); the load sets off 0.4 + 0.6·u₃ before the fold ends and
    arrives at 8.3 + 0.6·u₄; the unfold (turning u₆ then polar u₇, or together) starts 0.3·u₅
    after the load has covered 70 % of its way. Then, round by round, a flight whose
    reference comes within `PLAN_MARGIN` of an obstacle, the floor or ceiling, or another
    quad has its move (if that happens in the first half of the move) or its unfold (second
    half) delayed by `PLAN_STEP`. A flight still too close after `PLAN_ROUNDS` is flown as
    planned and rejected by the checks if it fails them.

    Args:
        inputs: `start [B, 3]`, `goal [B, 3]`, `phase [B]`, `timing [B, 8]`.
        horizon: the last output time.
        n: N. cable: d.
    """
    scale = horizon / 10.0
    u = inputs["timing"]
    alpha, _, polar, turn = formation(inputs["phase"], n, cable)
    polar_time = torch.sqrt(5.77 * cable * (polar - alpha).abs().amax(1) / FORMATION_ACCEL)
    turn_time = torch.sqrt(5.77 * cable * (torch.sin(polar) * turn.abs()).amax(1)
                           / FORMATION_ACCEL)  # fmt: skip
    if n % 2:
        polar_time = turn_time = torch.maximum(polar_time, turn_time)
    polar_time, turn_time = polar_time.clamp_min(0.3), turn_time.clamp_min(0.3)
    fold_polar, fold_turn = polar_time * (1 + 0.25 * u[:, 1]), turn_time * (1 + 0.25 * u[:, 2])
    open_turn, open_polar = turn_time * (1 + 0.25 * u[:, 6]), polar_time * (1 + 0.25 * u[:, 7])
    if n % 2:
        fold_turn, open_polar = fold_polar, open_turn
    fold_start = 0.3 * u[:, 0] * scale
    fold_turn_start = fold_start if n % 2 else fold_start + fold_polar
    fold_end = torch.maximum(fold_start + fold_polar, fold_turn_start + fold_turn)
    move_start = fold_end - (0.4 + 0.6 * u[:, 3]) * scale
    move_end = (8.3 + 0.6 * u[:, 4]) * scale
    # The min-jerk blend reaches 0.7 at τ ≈ 0.593.
    open_start = move_start + 0.593 * (move_end - move_start) + 0.3 * u[:, 5] * scale

    def build() -> Reference:
        open_polar_start = open_start if n % 2 else open_start + open_turn
        timing = torch.stack((fold_start, fold_polar, fold_turn_start, fold_turn, move_start,
                              move_end - move_start, open_start, open_turn, open_polar_start,
                              open_polar), dim=1)  # fmt: skip
        return Reference(inputs["start"], inputs["goal"], inputs["phase"], timing, n, cable)

    grid = torch.arange(0.0, horizon + 1e-9, PLAN_DT, dtype=torch.float64)
    for _ in range(PLAN_ROUNDS):
        ref = build()
        first_bad = torch.full_like(fold_start, math.inf)
        for t in grid.flip(0):  # backwards: the earliest violation is written last
            t_b = t.expand_as(fold_start)
            margin = torch.stack(list(clearances(ref.quads(t_b)[0], ref.load(t_b)[0]).values()),
                                 dim=1).amin(1)  # fmt: skip
            first_bad = torch.where(margin < PLAN_MARGIN, t, first_bad)
        bad = torch.isfinite(first_bad)
        if not bool(bad.any()):
            break
        early = first_bad < 0.5 * (move_start + move_end)
        move_start = torch.where(bad & early, move_start + PLAN_STEP * scale, move_start)
        open_start = torch.where(bad & ~early, open_start + PLAN_STEP * scale, open_start)
    return build()


def clearances(r_quads: torch.Tensor, r_load: torch.Tensor) -> dict[str, torch.Tensor]:
    """Signed clearances (m, negative = violation) of swarm positions.

    Args:
        r_quads: `[B, N, 3]`; r_load: `[B, 3]`.

    Returns:
        `[B]` each: `obstacle` (quads, load and cables against the doorway's cylinders),
        `room` (quads and load within 0 ≤ z ≤ ceiling) and `separation` (between quads).
    """
    axes = torch.tensor(CYLINDERS, dtype=r_quads.dtype)  # [C, 2]
    quad_xy, load_xy = r_quads[..., :2], r_load[:, None, :2]  # [B, N, 2], [B, 1, 2]
    quad_gap = torch.cdist(quad_xy, axes[None]).amin((1, 2)) - CYLINDER_RADIUS - QUAD_RADIUS
    load_gap = torch.cdist(load_xy, axes[None]).amin((1, 2)) - CYLINDER_RADIUS - LOAD_RADIUS
    # Cables are straight segments load → quad; the cylinders are vertical, so in plan view.
    seg = quad_xy - load_xy  # [B, N, 2]
    rel = axes[None, None] - load_xy[:, :, None]  # [B, 1, C, 2]
    along = (rel * seg[:, :, None]).sum(-1) / (seg * seg).sum(-1, keepdim=True).clamp_min(1e-12)
    nearest = load_xy[:, :, None] + along.clamp(0.0, 1.0)[..., None] * seg[:, :, None]
    cable_gap = (torch.linalg.vector_norm(nearest - axes, dim=-1).amin((1, 2))
                 - CYLINDER_RADIUS)  # fmt: skip
    z = torch.cat((r_quads[..., 2], r_load[:, 2:3]), dim=1)  # [B, N + 1]
    room = torch.minimum(CEILING - z, z).amin(1)
    dist = torch.cdist(r_quads, r_quads)  # [B, N, N]
    n = r_quads.shape[1]
    dist = dist + torch.eye(n, dtype=dist.dtype) * 1e9
    separation = dist.amin((1, 2)) - 2 * QUAD_RADIUS
    obstacle = torch.minimum(torch.minimum(quad_gap, load_gap), cable_gap)
    return {"obstacle": obstacle, "room": room, "separation": separation}


def fly(params: dict[str, float], y0: torch.Tensor, ts: torch.Tensor,
        inputs: dict[str, torch.Tensor], *, solver: SolverOptions,
        progress: Callable[[float], None] | None = None) -> Simulation:
    """Fly B flights from their hover `y0 [B, N, 13]` and sample them at `ts [T]`.

    Args:
        params: the system's scalar parameters.
        y0: `[B, N, 13]` float64; the load starts at rest at `inputs["start"]`.
        ts: `[T]` float64 output times; each interval is split into equal control holds of
            at most `CONTROL_DT`.
        inputs: `Quadrotor.sample`'s draws.
        solver: how each control hold is integrated (the generate config's `solver`).
        progress: called at each sample time with the fraction of the horizon flown.

    Raises:
        ValueError: a horizon shorter than `MIN_HORIZON`.

    Returns:
        A `Simulation` with controls `[B, T, N, 5]` (each interval's mean rotor forces and
        mean cable tension; the last sample holds the commands and tension at the last
        time), hidden `load [B, T, 6]` and `load_reference [B, T, 3]`, rejections, and
        diagnostics `cable_error`, `obstacle`, `room`, `separation`, `goal_error`,
        `saturation` (`[B]` each).
    """
    if float(ts[-1]) < MIN_HORIZON:
        raise ValueError(
            f"a quadrotor flight needs t_end >= {MIN_HORIZON:g} s to carry the load 6 m "
            f"through the doorway, got {float(ts[-1]):g} (the paper's is 10)"
        )
    p = QuadParams(params)
    batch, n = y0.shape[:2]
    ref = plan_reference(inputs, float(ts[-1]), n, p.cable)
    pilot = _Pilot(Controller(ref, p), p, n, batch, y0.dtype)
    load0 = torch.cat((inputs["start"], torch.zeros_like(inputs["start"])), dim=1)
    y = torch.cat((y0.reshape(batch, -1), load0, torch.zeros(batch, n, dtype=y0.dtype)), 1)
    # The hover's rotor forces, as if held before t = 0 (what the first tension reading sees).
    w = hover_state(inputs["start"], circle_directions(inputs["phase"], n, p.cable), p)[1]

    n_out = ts.numel()
    states = torch.full((batch, n_out, n, 13), math.nan, dtype=y0.dtype)
    controls = torch.full((batch, n_out, n, 5), math.nan, dtype=y0.dtype)
    load = torch.full((batch, n_out, 6), math.nan, dtype=y0.dtype)
    load_ref = torch.stack([ref.load(t.expand(batch))[0] for t in ts], dim=1)  # [B, T, 3]
    status = torch.zeros(batch, dtype=torch.long)
    n_f = torch.zeros(batch, dtype=torch.long)
    for k in range(n_out):
        states[:, k], load[:, k], _ = split_state(y, n)
        if progress is not None:
            progress(k / max(n_out - 1, 1))
        if k == n_out - 1:
            break
        y, w, status, controls[:, k] = _fly_interval(pilot, y, w, float(ts[k]),
                                                     float(ts[k + 1]), status, n_f, solver)
    controls[:, -1] = pilot.last_controls(float(ts[-1]), y, w)

    ok = status == Status.SUCCESS
    for array in (states, controls, load):
        array[~ok] = math.nan
    goal_error = torch.linalg.vector_norm(load[:, -1, 0:3] - inputs["goal"], dim=1)
    diagnostics = pilot.diagnostics(goal_error)
    return Simulation(
        states=states, status=status, n_f_evals=n_f, controls=controls,
        hidden={"load": load, "load_reference": load_ref},
        rejected=_rejected(diagnostics) & ok, diagnostics=diagnostics,
    )  # fmt: skip


class _Pilot:
    """The digital controller, and the checks made at each of its updates: the worst cable
    length error and clearances seen so far, and how many updates saturated a rotor.

    Args:
        controller: the flights' controller. p: the parameters.
        n: N. batch: B. dtype: the checks' float dtype.
    """

    def __init__(self, controller: Controller, p: QuadParams, n: int, batch: int,
                 dtype: torch.dtype) -> None:
        self.controller, self.p, self.n, self.dtype = controller, p, n, dtype
        self.cable_error = torch.zeros(batch, dtype=dtype)
        self.worst = {key: torch.full((batch,), math.inf, dtype=dtype)
                      for key in ("obstacle", "room", "separation")}  # fmt: skip
        self.n_saturated = torch.zeros(batch, dtype=torch.long)
        self.n_updates = 0

    def update(self, t: float, y: torch.Tensor, w_prev: torch.Tensor) -> torch.Tensor:
        """Check the state `y [B, F]` and compute new rotor forces `[B, N, 4]` at a control
        update, from the forces `w_prev` held until now (the cables' tension reading)."""
        p = self.p
        quads, load_now, _ = split_state(y, self.n)
        f_prev, _ = rotor_wrench(quads[..., 3:7], w_prev, p)
        tension, u = cable_tensions(quads, load_now, f_prev, p)
        length = torch.linalg.vector_norm(quads[..., 0:3] - load_now[:, None, 0:3], dim=-1)
        self.cable_error = torch.maximum(self.cable_error, (length - p.cable).abs().amax(1))
        for key, value in clearances(quads[..., 0:3], load_now[:, 0:3]).items():
            self.worst[key] = torch.minimum(self.worst[key], value)
        w_new, saturated = self.controller(t, quads, tension, u)
        self.n_saturated = self.n_saturated + saturated.any(1)
        self.n_updates += 1
        return w_new

    def last_controls(self, t: float, y: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """The last sample's controls `[B, N, 5]`: the commands computed there (an update,
        checked as the others) and the tension they produce."""
        w = self.update(t, y, w)
        quads, load_now, _ = split_state(y, self.n)
        f_last, _ = rotor_wrench(quads[..., 3:7], w, self.p)
        tension = cable_tensions(quads, load_now, f_last, self.p)[0]
        return torch.cat((w, tension[..., None]), dim=-1)

    def diagnostics(self, goal_error: torch.Tensor) -> dict[str, torch.Tensor]:
        """The checks, `[B]` each, with the load's distance from its goal at the end."""
        return {
            "cable_error": self.cable_error,
            **self.worst,
            "goal_error": goal_error,
            "saturation": self.n_saturated.to(self.dtype) / self.n_updates,
        }


def _fly_interval(pilot: _Pilot, y: torch.Tensor, w: torch.Tensor, t0: float, t1: float,
                  status: torch.Tensor, n_f: torch.Tensor, solver: SolverOptions
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Fly from one output time `t0` to the next, `t1`, in equal control holds of at most
    `CONTROL_DT`, each integrated with the rotor forces held.

    Args:
        pilot: the controller and its checks. y: the state `[B, F]` at t0. w: the rotor
            forces `[B, N, 4]` held until t0. status: `[B]` the flights' solver status so
            far. n_f: `[B]` right-hand-side evaluations, added to in place.
        solver: how each hold is integrated.

    Returns:
        The state and rotor forces at t1, the status, and the interval's controls
        `[B, N, 5]` (mean rotor forces and mean cable tension).
    """
    n, p = pilot.n, pilot.p
    _, _, integral0 = split_state(y, n)
    integral0 = integral0.clone()
    holds = max(1, math.ceil((t1 - t0) / CONTROL_DT - 1e-9))
    w_sum = torch.zeros_like(w)
    for j in range(holds):
        ta, tb = t0 + (t1 - t0) * j / holds, t0 + (t1 - t0) * (j + 1) / holds
        w = pilot.update(ta, y, w)
        w_sum += w * (tb - ta)
        y = _renormalize(y, n)
        w_hold = w
        sol = solve(lambda t, yy, w_hold=w_hold: swarm_rhs(yy, w_hold, n, p), y,
                    torch.tensor([ta, tb], dtype=torch.float64), **solver.solve_kwargs(),
                    dt0=tb - ta)  # fmt: skip
        n_f += sol.stats["n_f_evals"]
        failed = (sol.status != Status.SUCCESS) & (status == Status.SUCCESS)
        status = torch.where(failed, sol.status, status)
        # A failed flight is frozen at its last finite state (and reported NaN), so that
        # its NaN cannot reach the batched linear solves of the others.
        y = torch.where((status == Status.SUCCESS)[:, None], sol.ys[:, -1], y)
    _, _, integral1 = split_state(y, n)
    mean_tension = (integral1 - integral0) / (t1 - t0)
    return y, w, status, torch.cat((w_sum / (t1 - t0), mean_tension[..., None]), dim=-1)


def _rejected(diagnostics: dict[str, torch.Tensor]) -> torch.Tensor:
    """`[B]` the flights that fail a check (NaN anywhere fails every comparison, so it is
    rejected too)."""
    d = diagnostics
    return ~(
        (d["cable_error"] < MAX_CABLE_ERROR)
        & (d["obstacle"] >= 0) & (d["room"] >= 0) & (d["separation"] >= 0)
        & (d["goal_error"] <= GOAL_TOLERANCE)
        & (d["saturation"] < MAX_SATURATION)
    )  # fmt: skip


def _renormalize(y: torch.Tensor, n: int) -> torch.Tensor:
    """The state with unit quaternions (the solver's drift is ~1e-10; this keeps it there)."""
    y = y.clone()
    quads = y[:, : 13 * n].view(y.shape[0], n, 13)
    quads[..., 3:7] /= torch.linalg.vector_norm(quads[..., 3:7], dim=-1, keepdim=True)
    return y
