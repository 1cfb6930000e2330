"""Physics of N quadrotors carrying a point-mass load on rigid cables (paper eq. 9, App. A.5).

Everything here is batched torch in the caller's dtype, with no Python loop over flights.

Quadrotor (Jackson et al., RA-L 2020; TrajectoryOptimization.jl `examples/RA-L/models.jl`):
state 13 = position r, unit quaternion q (scalar first, body → world), world-frame velocity
v, body rates ω. Rotor forces w₁..₄ (kf = 1, so w is a force in N) in a "+" layout, rotor 1
on +x, 2 on +y, 3 on −x, 4 on −y:

    ṙ = v,   q̇ = ½ q ⊗ (0, ω),   v̇ = g + (R(q)·(0, 0, Σw) + F_cable)/m,
    ω̇ = J⁻¹(τ − ω × Jω),   τ = (L(w₂ − w₄), L(w₃ − w₁), km(w₁ − w₂ + w₃ − w₄)).

Load: point mass, state 6 = position r_L and velocity v_L, v̇_L = g + Σ_i s_i u_i / m_L, where
u_i = (r_i − r_L)/‖r_i − r_L‖ points from the load to quad i and s_i ≥ 0 is the tension of
cable i; the same cable pulls quad i with −s_i u_i.

Tension law (the authors' optimizer imposed the cable length as a constraint at its knot
points; a simulator needs a force law instead). The cables are rigid when taut: with
e_i = r_i − r_L and C_i = ½(‖e_i‖² − d²), the tensions are those that make

    C̈_i + 2β Ċ_i + β² C_i = 0        (Baumgarte stabilisation of length and length-rate drift)

for every taut cable. C̈_i is linear in s, which gives the N × N system M s = h with

    M = I/m + U Uᵀ/m_L   (U: rows u_i; symmetric positive definite, so always solvable),
    h_i = (‖ė_i‖² + e_i·f_i/m + 2β Ċ_i + β² C_i) / ‖e_i‖   (f_i: quad i's rotor force).

A cable can pull but not push, so the tensions solve the linear complementarity problem
s ≥ 0, M s − h ≥ 0, sᵀ(M s − h) = 0: a cable whose tension would be negative goes slack
(carries nothing) and may then shorten. It is solved by a few rounds of active-set updates,
exact whenever every cable is taut (the flights' usual case; a flight with a slack cable
fails the length check anyway). Re-tautening is not an impulse: the Baumgarte term pulls the
length back within ~1/β.
"""

from __future__ import annotations

import torch

# Baumgarte rate (1/s): length errors decay like (1 + βt)e^(−βt). Well below the solver's
# step-size limits, well above the flight's dynamics (pendulum modes ~3 rad/s).
BAUMGARTE = 10.0
GRAVITY_Z = -9.81
QUAD_DIM = 13
LOAD_DIM = 6


def quat_multiply(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product p ⊗ q of scalar-first quaternions `[..., 4]`."""
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - (pv * qv).sum(-1, keepdim=True)
    v = pw * qv + qw * pv + torch.linalg.cross(pv, qv, dim=-1)
    return torch.cat((w, v), dim=-1)


def rotation_matrix(q: torch.Tensor) -> torch.Tensor:
    """R(q) `[..., 3, 3]`, body → world, of scalar-first quaternions `[..., 4]`.

    The quaternion is normalized first, so a solver's tiny norm drift does not scale forces.
    """
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def quaternion_from_matrix(rot: torch.Tensor) -> torch.Tensor:
    """Scalar-first unit quaternion `[..., 4]` with w ≥ 0 of rotations `[..., 3, 3]`.

    Shepperd's method: each of the four candidate formulas is used where its pivot is the
    largest, which keeps the division well conditioned for every rotation.
    """
    m = rot
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    diag = torch.stack((trace, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]), dim=-1)  # [..., 4]
    pivot = diag.argmax(dim=-1)
    cands = []
    for k in range(4):
        if k == 0:
            t = 1 + trace
            c = (t, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                 m[..., 1, 0] - m[..., 0, 1])  # fmt: skip
        elif k == 1:
            t = 1 + m[..., 0, 0] - m[..., 1, 1] - m[..., 2, 2]
            c = (m[..., 2, 1] - m[..., 1, 2], t, m[..., 0, 1] + m[..., 1, 0],
                 m[..., 0, 2] + m[..., 2, 0])  # fmt: skip
        elif k == 2:
            t = 1 - m[..., 0, 0] + m[..., 1, 1] - m[..., 2, 2]
            c = (m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], t,
                 m[..., 1, 2] + m[..., 2, 1])  # fmt: skip
        else:
            t = 1 - m[..., 0, 0] - m[..., 1, 1] + m[..., 2, 2]
            c = (m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0],
                 m[..., 1, 2] + m[..., 2, 1], t)  # fmt: skip
        cands.append(torch.stack(c, dim=-1) * (0.5 / torch.sqrt(t.clamp_min(1e-12)))[..., None])
    q = torch.stack(cands, dim=-2)  # [..., 4 candidates, 4]
    q = torch.gather(q, -2, pivot[..., None, None].expand(*pivot.shape, 1, 4)).squeeze(-2)
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


class QuadParams:
    """The physical constants as plain floats and small tensors (one place, one dtype).

    Args:
        params: the system's scalar parameters (`Quadrotor.defaults` names).
        dtype, device: of the tensors.
    """

    def __init__(self, params: dict[str, float], dtype=torch.float64, device=None):
        self.m = params["m"]
        self.m_load = params["m_load"]
        self.arm = params["arm"]
        self.km = params["km"]
        self.w_max = params["w_max"]
        self.cable = params["cable"]
        self.g = params["g"]
        self.inertia = torch.tensor([params["Jxx"], params["Jyy"], params["Jzz"]],
                                    dtype=dtype, device=device)  # fmt: skip
        self.gravity = torch.tensor([0.0, 0.0, -self.g], dtype=dtype, device=device)
        arm, km = self.arm, self.km
        # [Σw, τx, τy, τz] = mix @ w for the "+" layout (rotors +x, +y, −x, −y).
        self.mix = torch.tensor(
            [[1.0, 1.0, 1.0, 1.0], [0.0, arm, 0.0, -arm], [-arm, 0.0, arm, 0.0],
             [km, -km, km, -km]], dtype=dtype, device=device,
        )  # fmt: skip
        self.unmix = torch.linalg.inv(self.mix)


def rotor_wrench(q: torch.Tensor, w: torch.Tensor, p: QuadParams):
    """World-frame rotor force and body torque of each quad.

    Args:
        q: `[..., 4]` attitudes; w: `[..., 4]` rotor forces.

    Returns:
        `(f [..., 3] world force, tau [..., 3] body torque)`.
    """
    rot = rotation_matrix(q)  # [..., 3, 3]
    thrust = w.sum(-1, keepdim=True)  # [..., 1]
    f = rot[..., :, 2] * thrust
    w1, w2, w3, w4 = w.unbind(-1)
    tau = torch.stack(
        (p.arm * (w2 - w4), p.arm * (w3 - w1), p.km * (w1 - w2 + w3 - w4)), dim=-1
    )
    return f, tau


def rigid_body_rhs(x: torch.Tensor, f: torch.Tensor, tau: torch.Tensor, p: QuadParams):
    """d/dt of quadrotor states under a world force and a body torque.

    Args:
        x: `[..., 13]` (r, q, v, ω); f: `[..., 3]` total non-gravity world force (rotors and
            cable); tau: `[..., 3]` body torque.

    Returns:
        `[..., 13]`.
    """
    q, v, om = x[..., 3:7], x[..., 7:10], x[..., 10:13]
    q_dot = 0.5 * quat_multiply(q, torch.cat((torch.zeros_like(om[..., :1]), om), dim=-1))
    v_dot = p.gravity + f / p.m
    j_om = p.inertia * om
    om_dot = (tau - torch.linalg.cross(om, j_om, dim=-1)) / p.inertia
    return torch.cat((v, q_dot, v_dot, om_dot), dim=-1)


def cable_tensions(quads: torch.Tensor, load: torch.Tensor, f: torch.Tensor, p: QuadParams):
    """Tensions of the rigid cables (see the module docstring) and their directions.

    Args:
        quads: `[B, N, 13]`; load: `[B, 6]`; f: `[B, N, 3]` world rotor forces.

    Returns:
        `(s [B, N] ≥ 0, u [B, N, 3] unit vectors load → quad)`.
    """
    e = quads[..., 0:3] - load[:, None, 0:3]  # [B, N, 3]
    e_dot = quads[..., 7:10] - load[:, None, 3:6]
    length = torch.linalg.vector_norm(e, dim=-1)  # [B, N]
    u = e / length[..., None]
    c = 0.5 * (length**2 - p.cable**2)
    c_dot = (e * e_dot).sum(-1)
    beta = BAUMGARTE
    h = ((e_dot * e_dot).sum(-1) + (e * f).sum(-1) / p.m + 2 * beta * c_dot + beta**2 * c) / length
    n = u.shape[1]
    eye = torch.eye(n, dtype=u.dtype, device=u.device)
    m_mat = eye / p.m + (u @ u.transpose(1, 2)) / p.m_load  # [B, N, N]
    return _complementarity(m_mat, h, eye), u


def _complementarity(m_mat: torch.Tensor, h: torch.Tensor, eye: torch.Tensor) -> torch.Tensor:
    """s ≥ 0 with M s − h ≥ 0 and sᵀ(M s − h) = 0, for SPD `m_mat [B, N, N]`, `h [B, N]`.

    Active-set rounds: solve with the taut cables, drop those that would push, re-take those
    that would stretch. Taut everywhere (the usual case) costs one solve and one check.
    """
    active = torch.ones_like(h, dtype=torch.bool)
    s = torch.linalg.solve(m_mat, h)
    for _ in range(2 * h.shape[1]):
        w = (m_mat @ s[..., None]).squeeze(-1) - h
        new = torch.where(active, s > 0, w < 0)
        if bool((new == active).all()):
            break
        active = new
        both = active[:, :, None] & active[:, None, :]
        s = torch.linalg.solve(torch.where(both, m_mat, eye), torch.where(active, h, 0.0))
    return torch.where(active, s, 0.0).clamp_min(0.0)


def swarm_rhs(y: torch.Tensor, w: torch.Tensor, n: int, p: QuadParams) -> torch.Tensor:
    """d/dt of the flat swarm state with rotor forces held.

    Args:
        y: `[B, F]`, F = 13N + 6 + N: the quads `[B, N, 13]` flattened, the load `[B, 6]`,
            and the running integral of each cable's tension `[B, N]` (so that a caller can
            read the mean tension over an interval exactly).
        w: `[B, N, 4]` rotor forces.
        n: N.

    Returns:
        `[B, F]`.
    """
    batch = y.shape[0]
    quads = y[:, : QUAD_DIM * n].view(batch, n, QUAD_DIM)  # [B, N, 13]
    load = y[:, QUAD_DIM * n : QUAD_DIM * n + LOAD_DIM]  # [B, 6]
    f_rotor, tau = rotor_wrench(quads[..., 3:7], w, p)  # [B, N, 3] each
    s, u = cable_tensions(quads, load, f_rotor, p)
    pull = s[..., None] * u  # [B, N, 3], on the load; the quad gets the opposite
    quad_dot = rigid_body_rhs(quads, f_rotor - pull, tau, p)  # [B, N, 13]
    load_acc = p.gravity + pull.sum(1) / p.m_load  # [B, 3]
    return torch.cat((quad_dot.reshape(batch, -1), load[:, 3:6], load_acc, s), dim=1)


def split_state(y: torch.Tensor, n: int):
    """`[B, F]` → `(quads [B, N, 13], load [B, 6], tension integrals [B, N])` (views)."""
    batch = y.shape[0]
    quads = y[:, : QUAD_DIM * n].view(batch, n, QUAD_DIM)
    load = y[:, QUAD_DIM * n : QUAD_DIM * n + LOAD_DIM]
    return quads, load, y[:, QUAD_DIM * n + LOAD_DIM :]
