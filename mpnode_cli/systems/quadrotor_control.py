"""Flights for the quadrotor swarm: the reference a flight follows and the controller that flies it.

This stands in for the authors' trajectory optimizer (ALTRO on the doorway problem of
Jackson et al., RA-L 2020), which was never released as a data generator.

Reference (`Reference`): the load follows a minimum-jerk path from its start to its goal.
The quads sit on the sphere of radius d (the cable length) around the load's reference, at
unit directions u_i from the load: a circle of radius 1.2 m (polar angle α = asin(1.2/d),
the authors' `r_config`) with a random phase, which folds into a fan in the x–z plane to
pass the doorway and opens again after it (two minimum-jerk phases each way, see
`Reference`). Quad i's reference is r_L + d·u_i, with its first two derivatives.

Controller (`Controller`), per quad, digital at `CONTROL_DT` with the rotor forces held in
between (a real flight controller's rate; holding them for a whole 0.2 s sample, or 0.1 s,
makes this cascade unstable, see `docs/quadrotor.md`):
1. position: a = a_ref + Kp (r_ref − r) + Kd (v_ref − v);
2. tension feed-forward: the rotor force must also cancel the cable's pull, F = m (a − g)
   + ŝ_i u_i, where ŝ is the tension measured at the update (the physics' tension at the
   current state under the forces held so far, i.e. a load cell) projected onto the
   tensions that hold the load (`_supporting`). The projection drops internal modes —
   cables pulling against each other, possible when the quads are coplanar (the fan) or
   more than three — which the loop would otherwise pass on unchanged from one update to
   the next (a neutral mode) instead of letting them decay. Without any feed-forward the
   0.9 kg load sags the formation by tens of centimetres (the position loop alone would
   need integral action);
3. attitude: the body z axis along F, yaw zero; thrust F·b₃; torque from the geometric SO(3)
   controller of Lee, Leok & McClamroch (CDC 2010) with the gyroscopic term cancelled;
4. mixing: rotor forces = mix⁻¹ [thrust, τ]; where that leaves [0, w_max], the torque is
   scaled down (thrust kept) until it fits, then the forces are clipped. A rotor whose
   unconstrained command lay outside [0, w_max] counts as saturated.
"""

from __future__ import annotations

import math

import torch

from mpnode_cli.systems.quadrotor_dynamics import (
    QuadParams,
    quaternion_from_matrix,
    rotation_matrix,
)

CONTROL_DT = 0.01  # s: 100 Hz, rotor forces held in between
# Position loop: natural frequency 2.5 rad/s, critically damped.
KP, KD = 6.25, 5.0
# Attitude loop (per unit inertia): natural frequency 20 rad/s, damping 0.8.
KR, KW = 400.0, 32.0
# Tension modes of the cable net whose eigenvalue of UᵀU (a 3 × 3 Gram matrix) is well below
# this are treated as internal (not holding the load) by the feed-forward.
SUPPORT_EPS = 1e-3

CIRCLE_RADIUS = 1.2  # m, the authors' r_config


def min_jerk(tau: torch.Tensor):
    """The minimum-jerk blend s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ on [0, 1], clamped outside.

    Returns:
        `(s, ds/dτ, d²s/dτ²)`, each shaped like `tau`.
    """
    inside = (tau > 0) & (tau < 1)
    t = tau.clamp(0.0, 1.0)
    s = t**3 * (10 - 15 * t + 6 * t**2)
    ds = torch.where(inside, 30 * t**2 * (1 - t) ** 2, 0.0)
    dds = torch.where(inside, 60 * t * (1 - t) * (1 - 2 * t), 0.0)
    return s, ds, dds


def fan_angles(n: int) -> list[float]:
    """Angles (rad) from the vertical of the fan's cables in the x–z plane, ascending.

    ±50° for three quads (the authors' β); wider for more, so that neighbouring slots stay
    26° apart (0.70 m between quads on 1.55 m cables).
    """
    half = max(math.radians(50.0), (n - 1) * math.radians(26.0) / 2)
    return [-half + 2 * half * i / (n - 1) for i in range(n)]


def formation(phase: torch.Tensor, n: int, cable: float):
    """Where each quad sits on the circle and where it goes in the fan, for `phase [B]`.

    A quad's direction from the load is given by its polar angle θ (from the vertical) and
    its azimuth φ. On the circle θ = α = asin(1.2/d) and φ_i = phase + 2πi/N. Fan slots are
    assigned in the x order of the quads on the circle; slot angle β_i > 0 means polar angle
    β_i at azimuth 0 (+x side), β_i < 0 means |β_i| at azimuth π.

    Returns:
        `(alpha, azimuth [B, N], polar [B, N] fan polar angles, turn [B, N])`, where `turn`
        is the signed azimuth change (|turn| ≤ π) that takes a quad to its fan side.
    """
    alpha = math.asin(CIRCLE_RADIUS / cable)
    azimuth = phase[:, None] + 2 * math.pi * torch.arange(n, dtype=phase.dtype) / n  # [B, N]
    slots = torch.tensor(fan_angles(n), dtype=phase.dtype)
    rank = torch.argsort(torch.argsort(torch.cos(azimuth), dim=1), dim=1)  # [B, N] x order
    beta = slots[rank]
    target = torch.where(beta < 0, math.pi, 0.0)
    # The pole (β = 0) has no azimuth: such a quad does not turn.
    turn = torch.where(beta == 0, 0.0, torch.remainder(target - azimuth + math.pi, 2 * math.pi)
                       - math.pi)  # fmt: skip
    return alpha, azimuth, beta.abs(), turn


def circle_directions(phase: torch.Tensor, n: int, cable: float) -> torch.Tensor:
    """`[B, N, 3]` unit vectors load → quad on the circle of radius 1.2 m."""
    alpha, azimuth, _, _ = formation(phase, n, cable)
    return _unit(torch.full_like(azimuth, alpha), azimuth)[0]


def _unit(theta: torch.Tensor, phi: torch.Tensor):
    """u(θ, φ) and its partial derivatives u_θ, u_φ, u_θθ, u_θφ, u_φφ, each `[..., 3]`."""
    st, ct, sp, cp = torch.sin(theta), torch.cos(theta), torch.sin(phi), torch.cos(phi)
    zero = torch.zeros_like(theta)
    u = torch.stack((st * cp, st * sp, ct), -1)
    u_t = torch.stack((ct * cp, ct * sp, -st), -1)
    u_p = torch.stack((-st * sp, st * cp, zero), -1)
    u_tp = torch.stack((-ct * sp, ct * cp, zero), -1)
    u_pp = torch.stack((-st * cp, -st * sp, zero), -1)
    return u, u_t, u_p, -u, u_tp, u_pp


class Reference:
    """The planned flight of B swarms: load path and formation, with derivatives.

    A quad's polar angle and azimuth each blend between circle and fan by minimum jerk, on
    their own schedules (`timing`); `quadrotor_flight.plan_reference` chooses them. With an
    even number of quads the fold runs in two phases so that no two quads meet: first each
    quad moves along its meridian to its slot's polar angle (keeping its circle azimuth,
    360°/N from its neighbours), then it turns about the vertical to its fan side (the quads
    now sit at polar angles a slot spacing apart, and the two at the same angle are opposite
    each other and turn the same way). Each phase keeps opposite quads opposite, so the
    cables can always hold the load with positive tensions. With an odd number there are no
    opposite pairs, and the two blends run together (for three quads this is close to
    moving along great circles).

    Args:
        start, goal: `[B, 3]` load positions.
        phase: `[B]` circle phase (rad).
        timing: `[B, 10]` seconds, start and duration of: the fold's polar blend, the fold's
            turning, the load's move, the unfold's turning, the unfold's polar blend.
        n: N quads. cable: d.
    """

    def __init__(self, start, goal, phase, timing, n: int, cable: float):
        self.start, self.goal, self.timing = start, goal, timing
        self.n, self.cable = n, cable
        self.alpha, self.azimuth, self.polar, self.turn = formation(phase, n, cable)

    def load(self, t: torch.Tensor):
        """Load reference at times `t [B]` (each flight its own time).

        Returns:
            `(r, v, a)`, each `[B, 3]`.
        """
        t0, dur = self.timing[:, 4], self.timing[:, 5]
        s, ds, dds = min_jerk((t - t0) / dur)
        delta = self.goal - self.start
        return (self.start + s[:, None] * delta, (ds / dur)[:, None] * delta,
                (dds / dur**2)[:, None] * delta)  # fmt: skip

    def blends(self, t: torch.Tensor):
        """The polar and turning blends (0 circle, 1 fan) and their time derivatives.

        Returns:
            `((μ, μ̇, μ̈) polar, (ν, ν̇, ν̈) turning)`, each `[B]`.
        """
        fold_p, fold_pd, fold_t, fold_td, _, _, open_t, open_td, open_p, open_pd = (
            self.timing.unbind(1)
        )
        return (_bump(t, fold_p, fold_pd, open_p, open_pd),
                _bump(t, fold_t, fold_td, open_t, open_td))  # fmt: skip

    def directions(self, t: torch.Tensor):
        """Unit directions load → quad and their first two time derivatives, `[B, N, 3]`."""
        (mu, mu_d, mu_dd), (nu, nu_d, nu_dd) = (
            tuple(x[:, None] for x in blend) for blend in self.blends(t)
        )
        dtheta = self.polar - self.alpha  # [B, N]
        theta = self.alpha + mu * dtheta
        phi = self.azimuth + nu * self.turn
        th_d, th_dd = mu_d * dtheta, mu_dd * dtheta
        ph_d, ph_dd = nu_d * self.turn, nu_dd * self.turn
        u, u_t, u_p, u_tt, u_tp, u_pp = _unit(theta, phi)
        w = (th_d[..., None], ph_d[..., None], th_dd[..., None], ph_dd[..., None])
        u_dot = u_t * w[0] + u_p * w[1]
        u_ddot = (u_tt * w[0] ** 2 + 2 * u_tp * w[0] * w[1] + u_pp * w[1] ** 2
                  + u_t * w[2] + u_p * w[3])  # fmt: skip
        return u, u_dot, u_ddot

    def quads(self, t: torch.Tensor):
        """Quad references `(r, v, a)`, each `[B, N, 3]`, at times `t [B]`."""
        r_l, v_l, a_l = self.load(t)
        u, u_dot, u_ddot = self.directions(t)
        d = self.cable
        return (r_l[:, None] + d * u, v_l[:, None] + d * u_dot, a_l[:, None] + d * u_ddot)


def _bump(t, rise_start, rise_dur, fall_start, fall_dur):
    """A blend that rises 0 → 1 and later falls back to 0, both by minimum jerk.

    Returns:
        `(value, d/dt, d²/dt²)`, each `[B]`.
    """
    s1, ds1, dds1 = min_jerk((t - rise_start) / rise_dur)
    s2, ds2, dds2 = min_jerk((t - fall_start) / fall_dur)
    return (s1 - s2, ds1 / rise_dur - ds2 / fall_dur,
            dds1 / rise_dur**2 - dds2 / fall_dur**2)  # fmt: skip


def hover_state(load_pos: torch.Tensor, directions: torch.Tensor, p: QuadParams):
    """The swarm at rest in equilibrium: quads on their cables, the load hanging still.

    Args:
        load_pos: `[B, 3]`; directions: `[B, N, 3]` unit vectors load → quad.

    Returns:
        `(quads [B, N, 13], w [B, N, 4] rotor forces, s [B, N] tensions)`.
    """
    s = _supporting_tensions(directions, -p.m_load * p.gravity.expand_as(load_pos))
    f = -p.m * p.gravity + s[..., None] * directions  # [B, N, 3] rotor force to hover
    rot = attitude(f)
    q = quaternion_from_matrix(rot)
    r = load_pos[:, None] + p.cable * directions
    zeros = torch.zeros_like(r)
    w = (torch.linalg.vector_norm(f, dim=-1) / 4)[..., None].expand(*f.shape[:-1], 4)
    return torch.cat((r, q, zeros, zeros), dim=-1), w.contiguous(), s


def attitude(force: torch.Tensor) -> torch.Tensor:
    """Rotation `[..., 3, 3]` with body z along `force [..., 3]` and zero yaw (body x in the
    world x–z plane)."""
    b3 = force / torch.linalg.vector_norm(force, dim=-1, keepdim=True)
    x_c = torch.zeros_like(b3)
    x_c[..., 0] = 1.0
    b2 = torch.linalg.cross(b3, x_c, dim=-1)
    b2 = b2 / torch.linalg.vector_norm(b2, dim=-1, keepdim=True)
    b1 = torch.linalg.cross(b2, b3, dim=-1)
    return torch.stack((b1, b2, b3), dim=-1)


def _supporting_tensions(u: torch.Tensor, force: torch.Tensor) -> torch.Tensor:
    """Least-norm tensions `[B, N]` with Σ s_i u_i = `force [B, 3]` (regularized)."""
    gram = u.transpose(1, 2) @ u  # [B, 3, 3]
    eye = torch.eye(3, dtype=u.dtype, device=u.device)
    return (u @ torch.linalg.solve(gram + 1e-12 * eye, force[..., None])).squeeze(-1)


def _supporting(u: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """The part of tensions `s [B, N]` that holds the load: U (UᵀU + εI)⁻¹ Uᵀ s.

    Tension modes in the null space of Uᵀ (cables pulling against each other) are removed; the
    regularization makes that a smooth function of the geometry as the quads become coplanar.
    """
    gram = u.transpose(1, 2) @ u  # [B, 3, 3]
    eye = torch.eye(3, dtype=u.dtype, device=u.device)
    net = (u.transpose(1, 2) @ s[..., None])  # [B, 3, 1]
    return (u @ torch.linalg.solve(gram + SUPPORT_EPS * eye, net)).squeeze(-1)


class Controller:
    """Cascaded position → attitude control with tension feed-forward, mixing, saturation.

    Args:
        reference: the flights' `Reference`.
        p: physical constants.
    """

    def __init__(self, reference: Reference, p: QuadParams):
        self.ref, self.p = reference, p

    def __call__(self, t: float, quads: torch.Tensor, tension: torch.Tensor, u: torch.Tensor):
        """Rotor forces to hold until the next update.

        Args:
            t: time of the update.
            quads: `[B, N, 13]` measured quad states.
            tension: `[B, N]` measured cable tensions; u: `[B, N, 3]` cable directions
                (load → quad).

        Returns:
            `(w [B, N, 4] rotor forces in [0, w_max], saturated [B, N] bool)`.
        """
        p = self.p
        batch = quads.shape[0]
        t_b = torch.full((batch,), t, dtype=quads.dtype)
        r_ref, v_ref, a_ref = self.ref.quads(t_b)
        r, q, v, om = quads[..., 0:3], quads[..., 3:7], quads[..., 7:10], quads[..., 10:13]
        acc = a_ref + KP * (r_ref - r) + KD * (v_ref - v)
        force = p.m * (acc - p.gravity) + _supporting(u, tension)[..., None] * u  # [B, N, 3]

        rot = rotation_matrix(q)  # [B, N, 3, 3]
        rot_d = attitude(force)
        thrust = (force * rot[..., :, 2]).sum(-1)  # [B, N]
        err = rot_d.transpose(-1, -2) @ rot - rot.transpose(-1, -2) @ rot_d
        e_r = 0.5 * torch.stack((err[..., 2, 1], err[..., 0, 2], err[..., 1, 0]), dim=-1)
        j_om = p.inertia * om
        tau = p.inertia * (-KR * e_r - KW * om) + torch.linalg.cross(om, j_om, dim=-1)
        return self._mix(thrust, tau)

    def _mix(self, thrust: torch.Tensor, tau: torch.Tensor):
        """Rotor forces for `thrust [B, N]` and `tau [B, N, 3]`, fitted into [0, w_max]."""
        p = self.p
        w_thrust = thrust[..., None] * p.unmix[:, 0]  # [B, N, 4]
        w_tau = tau @ p.unmix[:, 1:].T  # [B, N, 4]
        w = w_thrust + w_tau
        saturated = ((w < 0) | (w > p.w_max)).any(-1)
        # Largest k ∈ [0, 1] with w_thrust + k·w_tau inside the box, rotor by rotor.
        room = torch.where(w_tau > 0, p.w_max - w_thrust, -w_thrust)
        ratio = torch.where(w_tau.abs() > 1e-12, room / w_tau.where(w_tau.abs() > 1e-12, 1.0),
                            math.inf)  # fmt: skip
        k = ratio.amin(-1, keepdim=True).clamp(0.0, 1.0)
        return (w_thrust + k * w_tau).clamp(0.0, p.w_max), saturated
