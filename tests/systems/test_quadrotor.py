"""The quadrotor swarm: rigid-body physics, the cable law, the flights and their checks.

Physics is checked against closed forms (hover, free fall) and conservation laws (angular
momentum of a torque-free body; energy of a swarm on rigid cables, which do no work). The
flights are checked on a small dataset made by `generate`, from the stored arrays alone.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate, resolve_generate_config
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.solver import solve
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.systems import get_system
from mpnode_cli.systems import quadrotor_flight as qf
from mpnode_cli.systems.quadrotor import Quadrotor
from mpnode_cli.systems.quadrotor_control import circle_directions, hover_state
from mpnode_cli.systems.quadrotor_dynamics import (
    QuadParams,
    cable_tensions,
    quaternion_from_matrix,
    rigid_body_rhs,
    rotation_matrix,
    rotor_wrench,
    split_state,
    swarm_rhs,
)

SYSTEM = get_system("quadrotor")
P = QuadParams(SYSTEM.params)
TOL = {"rtol": 1e-10, "atol": 1e-12}


def _one_quad(w: torch.Tensor):
    """f(t, x [B, 13]) for free quadrotors with rotor forces `w [B, 4]` held."""

    def f(t, x):
        force, tau = rotor_wrench(x[:, 3:7], w, P)
        return rigid_body_rhs(x, force, tau, P)

    return f


def _quad(r=(0.0, 0.0, 1.0), q=(1.0, 0.0, 0.0, 0.0), v=(0.0, 0.0, 0.0), om=(0.0, 0.0, 0.0)):
    return torch.tensor([[*r, *q, *v, *om]], dtype=torch.float64)


# ----- one quadrotor ------------------------------------------------------------------------


def test_hover_at_static_thrust_stays_put():
    x0 = _quad(r=(0.3, -0.2, 1.5))
    w = torch.full((1, 4), P.m * P.g / 4, dtype=torch.float64)
    assert _one_quad(w)(0.0, x0).abs().max() < 1e-14
    sol = solve(_one_quad(w), x0, torch.linspace(0.0, 5.0, 11), **TOL)
    assert (sol.ys - x0[:, None]).abs().max() < 1e-12


def test_zero_thrust_is_free_fall():
    half = math.sqrt(0.5)
    x0 = _quad(r=(1.0, 2.0, 3.0), q=(half, half, 0.0, 0.0), v=(0.5, -1.0, 2.0))
    ts = torch.linspace(0.0, 2.0, 9, dtype=torch.float64)
    sol = solve(_one_quad(torch.zeros(1, 4, dtype=torch.float64)), x0, ts, **TOL)
    r0, v0 = x0[0, 0:3], x0[0, 7:10]
    expected = r0 + v0 * ts[:, None] + 0.5 * P.gravity * ts[:, None] ** 2  # [T, 3]
    torch.testing.assert_close(sol.ys[0, :, 0:3], expected, rtol=0, atol=1e-10)
    torch.testing.assert_close(sol.ys[0, :, 3:7], x0[:, 3:7].expand(9, 4), rtol=0, atol=1e-12)


def test_torque_free_rotation_conserves_angular_momentum_and_quaternion_norm():
    # A symmetric top spun off its axes: ω precesses in the body, R·J·ω stays fixed.
    x0 = _quad(q=(0.9, 0.1, -0.3, 0.2), om=(3.0, -2.0, 5.0))
    x0[:, 3:7] /= x0[:, 3:7].norm()
    sol = solve(_one_quad(torch.zeros(1, 4, dtype=torch.float64)), x0,
                torch.linspace(0.0, 3.0, 31), **TOL)  # fmt: skip
    q, om = sol.ys[0, :, 3:7], sol.ys[0, :, 10:13]
    momentum = (rotation_matrix(q) @ (P.inertia * om)[..., None]).squeeze(-1)  # [T, 3] world
    torch.testing.assert_close(momentum, momentum[:1].expand_as(momentum), rtol=0, atol=1e-10)
    assert (q.norm(dim=1) - 1).abs().max() < 1e-10
    energy = 0.5 * (P.inertia * om**2).sum(1)
    assert (energy - energy[0]).abs().max() < 1e-10
    assert (om[:, 0] - om[0, 0]).abs().max() > 0.1  # it did precess: a real test


def test_rotor_layout_and_quaternions():
    # "+" layout: the torque is Σ r_i × (0, 0, w_i) with rotors at +x, +y, −x, −y, plus the
    # drag moments ±km·w_i of rotors 1, 3 (one way) and 2, 4 (the other).
    w = torch.tensor([[1.0, 2.0, 3.0, 0.5]], dtype=torch.float64)
    arms = P.arm * torch.tensor([[1.0, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]]).double()
    lift = torch.zeros(4, 3, dtype=torch.float64)
    lift[:, 2] = w[0]
    drag = P.km * torch.tensor([1.0, -1.0, 1.0, -1.0]).double() @ w[0]
    expected = torch.linalg.cross(arms, lift).sum(0) + torch.tensor([0, 0, 1.0]).double() * drag
    force, tau = rotor_wrench(_quad()[:, 3:7], w, P)
    torch.testing.assert_close(tau[0], expected)
    torch.testing.assert_close(force[0], torch.tensor([0.0, 0.0, 6.5]).double())
    q = torch.randn(64, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    q = q / q.norm(dim=1, keepdim=True)
    q = torch.where(q[:, :1] < 0, -q, q)
    torch.testing.assert_close(quaternion_from_matrix(rotation_matrix(q)), q)
    rot = rotation_matrix(q)
    torch.testing.assert_close(rot @ rot.transpose(1, 2), torch.eye(3).double().expand(64, 3, 3))


# ----- the swarm on its cables --------------------------------------------------------------


def _hovering_swarm(n=3, phase=0.4):
    load = torch.tensor([[0.0, 0.0, 0.25]], dtype=torch.float64)
    dirs = circle_directions(torch.tensor([phase], dtype=torch.float64), n, P.cable)
    quads, w, s = hover_state(load, dirs, P)
    y = torch.cat((quads.reshape(1, -1), load, torch.zeros(1, 3 + n, dtype=torch.float64)), 1)
    return y, w, s


@pytest.mark.parametrize("n", [3, 6])
def test_swarm_hovers_in_equilibrium(n):
    y, w, s = _hovering_swarm(n)
    alpha = math.asin(1.2 / P.cable)
    # The RA-L code's static tension m_L g / (N cos α): 4.65 N for three quads.
    torch.testing.assert_close(s, torch.full_like(s, P.m_load * P.g / (n * math.cos(alpha))))
    dy = swarm_rhs(y, w, n, P)
    # Zero up to the rounding of the cable LCP's tension, which `hover_state` solved another
    # way (sqrt, LAPACK): ~2000 ulp of a ~5 N tension, ≈ 2e-12 on an AMD EPYC.
    assert dy[:, : 13 * n + 6].abs().max() < 1e-10
    torch.testing.assert_close(dy[:, 13 * n + 6 :], s)  # the tension integrals grow at s


def test_rigid_cables_keep_their_length_and_do_no_work():
    # Spin the hovering swarm about the vertical through the load, cut the rotors, and let it
    # fall: the cables pull the quads round (centripetal tension) but never change the
    # energy, and their lengths stay put.
    n = 3
    y, _, _ = _hovering_swarm(n)
    quads, load, _ = split_state(y, n)
    spin = torch.tensor([0.0, 0.0, 2.5], dtype=torch.float64)
    quads[..., 7:10] = torch.linalg.cross(spin.expand(1, n, 3), quads[..., 0:3] - load[:, None, :3])
    quads[..., 10:13] = torch.tensor([0.3, -0.2, 1.0])
    w = torch.zeros(1, n, 4, dtype=torch.float64)

    def energy(y):
        quads, load, _ = split_state(y, n)
        kinetic = 0.5 * P.m * (quads[..., 7:10] ** 2).sum((-1, -2))
        kinetic += 0.5 * (P.inertia * quads[..., 10:13] ** 2).sum((-1, -2))
        kinetic += 0.5 * P.m_load * (load[:, 3:6] ** 2).sum(-1)
        potential = P.g * (P.m * quads[..., 2].sum(-1) + P.m_load * load[:, 2])
        return kinetic + potential

    sol = solve(lambda t, yy: swarm_rhs(yy, w, n, P), y, torch.linspace(0, 2, 21), **TOL)
    ys = sol.ys[0]  # [T, F]
    quads, load, _ = split_state(ys, n)
    lengths = (quads[..., 0:3] - load[:, None, 0:3]).norm(dim=-1)
    assert (lengths - P.cable).abs().max() < 1e-9
    e = energy(ys)
    assert (e - e[0]).abs().max() < 1e-8 * e[0].abs()
    f, _ = rotor_wrench(quads[..., 3:7], w.expand(21, n, 4), P)
    s, _ = cable_tensions(quads, load, f, P)
    assert s.min() > 1.0  # taut all the way: the spin keeps the cables pulling


def test_a_cable_can_pull_but_not_push():
    n = 3
    y, w, _ = _hovering_swarm(n)
    quads, load, _ = split_state(y, n)
    quads[0, 0, 7:10] = -3.0 * (quads[0, 0, 0:3] - load[0, 0:3]) / P.cable  # quad 0 dives in
    f, _ = rotor_wrench(quads[..., 3:7], w, P)
    s, u = cable_tensions(quads, load, f, P)
    assert s[0, 0] == 0 and (s[0, 1:] > 0).all()
    # Complementarity: the slack cable is not being stretched, the taut ones are held exactly.
    from mpnode_cli.systems.quadrotor_dynamics import BAUMGARTE

    e = P.cable * u  # the lengths are exact here, so C = 0
    e_dot = quads[..., 7:10] - load[:, None, 3:6]
    m_mat = torch.eye(n).double() / P.m + u[0] @ u[0].T / P.m_load
    c_dot = (e * e_dot).sum(-1)
    h = ((e_dot**2).sum(-1) + (e * f).sum(-1) / P.m + 2 * BAUMGARTE * c_dot) / P.cable
    slack = (m_mat @ s[0] - h[0])
    assert slack[0] > 0 and slack[1:].abs().max() < 1e-12


# ----- flights ------------------------------------------------------------------------------


def test_clearances_see_every_kind_of_violation():
    load = torch.tensor([[0.0, 0.0, 0.25]] * 5, dtype=torch.float64)
    quads = torch.tensor([[[1.0, 0.0, 1.2], [-1.0, 0.5, 1.2], [-1.0, -0.5, 1.2]]] * 5,
                         dtype=torch.float64)  # fmt: skip
    quads[1, 0] = torch.tensor([2.5, 0.7, 1.2])  # a quad's rim inside a cylinder
    load[2] = torch.tensor([2.4, 0.0, 0.25])  # a cable from (2.4, 0) to (3.4, 0.2)...
    quads[2] += torch.tensor([2.4, 0.0, 0.0])
    quads[2, 0, 1] = 1.0  # ...now runs through the cylinder at (3, 1)
    quads[3, 1, 2] = 2.2  # above the ceiling
    quads[4, 2] = quads[4, 1] + torch.tensor([0.0, 0.3, 0.0])  # two quads 0.3 m apart
    c = qf.clearances(quads, load)
    assert (c["obstacle"][0] > 0) and (c["room"][0] > 0) and (c["separation"][0] > 0)
    assert c["obstacle"][1] < 0 and c["obstacle"][2] < 0
    assert c["room"][3] < 0 and c["separation"][4] < 0
    assert c["obstacle"][3] > 0 and c["obstacle"][4] > 0


@pytest.fixture(scope="module")
def quad3(tmp_path_factory):
    """Four quad3 flights of the shortest horizon made by `generate`: the dataset, its
    summary, and the `Simulation`s behind it (with the diagnostics the file does not keep).

    A flight costs the same per control update whatever the batch, so the suite flies one
    batch here and every flight test reads it.
    """
    sims = []
    simulate = Quadrotor.simulate

    def recording(self, *args, **kwargs):
        sims.append(simulate(self, *args, **kwargs))
        return sims[-1]

    config = GenerateConfig(system="quadrotor", nodes=3, trajectories=4, t_end=qf.MIN_HORIZON,
                            out=tmp_path_factory.mktemp("quad") / "quad3.h5")  # fmt: skip
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Quadrotor, "simulate", recording)
        summary = generate(config)
    return read_dataset(summary.path), summary, sims


def test_every_stored_flight_passes_the_checks(quad3):
    ds, summary, _ = quad3
    k, t, n = 4, 41, 3
    assert ds.states.shape == (k, t, n, 13) and ds.controls.shape == (k, t, n, 5)
    assert ds.hidden["load"].shape == (k, t, 6) and ds.hidden["load_reference"].shape == (k, t, 3)
    assert ds.control_names == ("w1", "w2", "w3", "w4", "tension")
    np.testing.assert_allclose(ds.time[-1], qf.MIN_HORIZON)
    assert (ds.adjacency[0] == 1 - np.eye(n)).all()  # complete graph among the quads
    assert ds.extra_attrs["n_rejected"] == summary.rejected

    quads = torch.from_numpy(ds.states.astype(np.float64))  # [K, T, N, 13]
    load = torch.from_numpy(ds.hidden["load"].astype(np.float64))  # [K, T, 6]
    lengths = (quads[..., 0:3] - load[:, :, None, 0:3]).norm(dim=-1)
    assert (lengths - P.cable).abs().max() < 0.01
    c = qf.clearances(quads[..., 0:3].reshape(k * t, n, 3), load[..., 0:3].reshape(k * t, 3))
    assert all(bool((value >= 0).all()) for value in c.values()), c
    goal = ds.hidden["load_reference"][:, -1]
    assert np.linalg.norm(ds.hidden["load"][:, -1, :3] - goal, axis=1).max() <= 0.3
    assert np.linalg.norm(goal - [6.0, 0.0, 0.25], axis=1).max() < 0.3
    assert np.abs(np.linalg.norm(ds.states[..., 3:7], axis=-1) - 1).max() < 1e-6
    w, s = ds.controls[..., :4], ds.controls[..., 4]
    assert w.min() >= 0 and w.max() <= P.w_max + 1e-6 and s.min() >= 0


def test_flights_report_their_checks_and_saturation(quad3):
    # What the stored arrays cannot show (rotor saturation, cable length between samples)
    # is in the simulation's diagnostics, and `rejected` is exactly their verdict.
    _, _, sims = quad3
    sim = sims[0]  # the first round: all four flights as drawn
    assert sim.states.shape[0] == 4
    d = sim.diagnostics
    verdict = ~((d["cable_error"] < qf.MAX_CABLE_ERROR) & (d["obstacle"] >= 0) & (d["room"] >= 0)
                & (d["separation"] >= 0) & (d["goal_error"] <= qf.GOAL_TOLERANCE)
                & (d["saturation"] < qf.MAX_SATURATION))  # fmt: skip
    assert torch.equal(sim.rejected, verdict) and not sim.rejected.any()
    assert d["cable_error"].max() < 1e-3 and d["saturation"].max() < qf.MAX_SATURATION
    # The stored tension is the interval mean of the physical one, hence near the static
    # share at the start (the swarm begins at rest in hover).
    alpha = math.asin(1.2 / P.cable)
    static = P.m_load * P.g / (3 * math.cos(alpha))
    assert abs(float(sim.controls[:, 0, :, 4].mean()) - static) < 0.2


def test_render_a_flight(quad3, tmp_path):
    from mpnode_cli.report.flight import plot_flight

    ds, _, _ = quad3
    path = plot_flight(ds.states[0], ds.hidden["load"][0], tmp_path / "f" / "flight.png",
                       reference=ds.hidden["load_reference"][0], time=ds.time)  # fmt: skip
    image = __import__("matplotlib.image").image.imread(path)
    assert image.ndim == 3 and min(image.shape[:2]) > 200


def test_presets_and_limits():
    for name, n in (("quad3", 3), ("quad6", 6)):
        from mpnode_cli.data.presets import get_preset

        config = resolve_generate_config(GenerateConfig(**get_preset(name)))
        assert (config.nodes, config.trajectories, config.num_steps, config.dt) == (n, 463, 50, 0.2)
    with pytest.raises(ValueError, match="not 5"):
        resolve_generate_config(GenerateConfig(system="quadrotor", nodes=5))
    y0, inputs = SYSTEM.sample(SYSTEM.graph("complete", 3, 0), 1, np.random.default_rng(0))
    with pytest.raises(ValueError, match="t_end >= 8"):
        SYSTEM.simulate(None, {}, torch.from_numpy(y0), torch.tensor([0.0, 5.0]).double(),
                        {name: torch.from_numpy(v) for name, v in inputs.items()},
                        solver=SolverOptions(rtol=1e-8, atol=1e-10))  # fmt: skip


def test_mpnode_trains_on_a_small_quad3_set(quad3, tmp_path):
    """MP-NODE with ZOH controls (the solver's `tstops` at control changes) on a few quad3
    flights: its validation loss falls."""
    from mpnode_cli.config.train import TrainConfig
    from mpnode_cli.training.loop import train
    from mpnode_cli.training.run import read_metrics

    _, summary, _ = quad3
    # The whole horizon from the first epoch (quadrotor data recommend a curriculum, which
    # in 8 epochs would still be on short prefixes).
    config = TrainConfig(dataset=summary.path, epochs=8, batch_size=4, lr=1e-2, plots=False,
                         run_dir=tmp_path / "run", model_options={"hidden": 16},
                         horizon_curriculum=False)
    result = train(config)
    rows = read_metrics(tmp_path / "run")
    assert result.best_epoch > 0
    assert rows[-1]["val_loss"] < 0.7 * rows[0]["val_loss"]

