"""Tests of the batched Runge–Kutta solvers against independent references, through
`solve(method=...)` and the methods' tableaus (`METHODS`).

References: the rooted-tree order conditions (computed here, not copied), closed-form
solutions, scipy's DOP853 at tight tolerance, and finite differences (gradcheck).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from conftest import rounding_apart
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from mpnode_cli.solver import METHODS, IController, PIController, Status, solve

ADAPTIVE = [name for name, tableau in METHODS.items() if tableau.adaptive]

# ----------------------------------------------------------------------------- order conditions


def rooted_trees(order: int):
    """All rooted trees with `order` vertices, as sorted tuples of child subtrees."""
    if order == 1:
        return [()]
    trees = set()
    # Children of the root: a multiset of trees whose sizes sum to order - 1.
    for sizes in _partitions(order - 1):
        for combo in itertools.product(*(rooted_trees(s) for s in sizes)):
            trees.add(tuple(sorted(combo)))
    return sorted(trees)


def _partitions(n, largest=None):
    largest = largest or n
    if n == 0:
        yield []
        return
    for k in range(min(n, largest), 0, -1):
        for rest in _partitions(n - k, k):
            yield [k, *rest]


def tree_size(t) -> int:
    return 1 + sum(tree_size(c) for c in t)


def gamma(t) -> int:
    return tree_size(t) * math.prod(gamma(c) for c in t)


def stage_weights(t, a: np.ndarray) -> np.ndarray:
    """Φ_i(t): product over children of Σ_j a_ij Φ_j(child); 1 for the single vertex."""
    phi = np.ones(a.shape[0])
    for child in t:
        phi = phi * (a @ stage_weights(child, a))
    return phi


def tableau_arrays(name: str):
    """`(a (s, s), b, e or None, c)` of a method, as numpy arrays."""
    t = METHODS[name]
    a = np.zeros((t.stages, t.stages))
    for i, row in enumerate(t.a):
        a[i, : len(row)] = row
    e = None if t.e is None else np.array(t.e)
    return a, np.array(t.b), e, np.array(t.c)


def with_end_stage(name: str):
    """`(a, c)` with, for a method that is not FSAL, the stage f(t + h, y₁) appended (a = b,
    c = 1): the stages the interpolant's rows refer to."""
    a, b, _, c = tableau_arrays(name)
    if METHODS[name].fsal:
        return a, c
    s = len(b)
    ext = np.zeros((s + 1, s + 1))
    ext[:s, :s], ext[s, :s] = a, b
    return ext, np.append(c, 1.0)


def test_number_of_trees_matches_known_counts():
    assert [len(rooted_trees(k)) for k in range(1, 7)] == [1, 1, 2, 4, 9, 20]


@pytest.mark.parametrize("name", METHODS)
def test_row_sums_are_the_nodes(name):
    a, _, _, c = tableau_arrays(name)
    np.testing.assert_allclose(a.sum(axis=1), c, atol=1e-14)


@pytest.mark.parametrize("name", METHODS)
def test_b_satisfies_the_order_conditions_of_its_order_and_no_more(name):
    a, b, _, _ = tableau_arrays(name)
    p = METHODS[name].order
    for order in range(1, p + 1):
        for t in rooted_trees(order):
            assert b @ stage_weights(t, a) == pytest.approx(1 / gamma(t), abs=1e-13), t
    residual = max(abs(b @ stage_weights(t, a) - 1 / gamma(t)) for t in rooted_trees(p + 1))
    assert residual > 1e-5


@pytest.mark.parametrize("name", ADAPTIVE)
def test_embedded_weights_have_their_order_but_not_more(name):
    a, b, e, _ = tableau_arrays(name)
    b_hat = b - e
    q = METHODS[name].error_order
    for order in range(1, q + 1):
        for t in rooted_trees(order):
            assert b_hat @ stage_weights(t, a) == pytest.approx(1 / gamma(t), abs=1e-13), t
    residual = max(abs(b_hat @ stage_weights(t, a) - 1 / gamma(t)) for t in rooted_trees(q + 1))
    assert residual > 1e-5  # otherwise the error estimate would not estimate anything
    assert e.sum() == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("name", METHODS)
def test_fsal_and_dense_output_conditions(name):
    tab = METHODS[name]
    a, _ = with_end_stage(name)
    b = np.array(tab.b) if tab.fsal else np.append(tab.b, 0.0)
    if tab.fsal:
        assert tab.c[-1] == 1.0 and tab.b[-1] == 0.0
        np.testing.assert_array_equal(a[-1, :-1], b[:-1])
    interp = np.array(tab.interp)  # (s, K): coefficients of θ, θ², ..., θ^K
    np.testing.assert_allclose(interp.sum(axis=1), b, atol=1e-14)  # b_i(1) = b_i
    for theta in (0.1, 0.37, 0.5, 0.8):
        b_theta = interp @ theta ** np.arange(1, interp.shape[1] + 1)
        for order in range(1, tab.dense_order + 1):
            for t in rooted_trees(order):
                want = theta ** tree_size(t) / gamma(t)
                assert b_theta @ stage_weights(t, a) == pytest.approx(want, abs=1e-12)


# ----------------------------------------------------------------------------- convergence

M = np.array([[-0.1, 1.0, 0.0], [-1.0, -0.1, 0.3], [0.0, -0.3, -0.5]])


def linear_exact(y0: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.stack([expm(M * tt) @ y0 for tt in t])


def observed_order(hs, errors) -> float:
    return float(np.polyfit(np.log(hs), np.log(errors), 1)[0])


def one_step(name: str, y0: np.ndarray, h: float):
    """A plain numpy step of y' = M y from the tableau's numbers: `(y₁, err or None, b(θ)
    → y(θh))`, an independent reading of the tableau to check `solve` against."""
    a, c = with_end_stage(name)
    tab = METHODS[name]
    k = np.zeros((len(c), len(y0)))
    for i in range(len(c)):
        k[i] = M @ (y0 + h * a[i, :i] @ k[:i])
    y1 = y0 + h * np.array(tab.b) @ k[: tab.stages]
    err = None if tab.e is None else h * np.array(tab.e) @ k[: tab.stages]
    interp = np.array(tab.interp)

    def dense(theta: float) -> np.ndarray:
        return y0 + h * (interp @ theta ** np.arange(1, interp.shape[1] + 1)) @ k

    return y1, err, dense


@pytest.mark.parametrize("name", METHODS)
def test_fixed_step_converges_with_its_order(name):
    y0 = np.array([1.0, 0.5, -0.3])
    mt = torch.tensor(M)
    ts = torch.tensor([0.0, 1.0, 2.0])
    exact = linear_exact(y0, ts.numpy())
    hs = [0.4, 0.2, 0.1, 0.05]
    errors = []
    for h in hs:
        sol = solve(lambda t, y: y @ mt.T, torch.tensor(y0)[None], ts, method=name, fixed_dt=h)
        errors.append(np.abs(sol.ys[0].numpy() - exact).max())
    order = observed_order(hs, errors)
    assert abs(order - METHODS[name].order) < 0.3, (order, errors)


@pytest.mark.parametrize("name", ADAPTIVE)
def test_embedded_solution_has_its_order_and_the_error_estimate_tracks_it(name):
    """y₁ − err (the embedded solution) has local error h^(q+1), and err ≈ that error
    (catches a wrong error weight)."""
    y0 = np.array([1.0, 0.5, -0.3])
    hs = [0.2, 0.1, 0.05, 0.025]
    local, ratios = [], []
    for h in hs:
        y1, err, _ = one_step(name, y0, h)
        true = expm(M * h) @ y0 - (y1 - err)
        local.append(np.abs(true).max())
        ratios.append(np.linalg.norm(err - true) / np.linalg.norm(true))
    q = METHODS[name].error_order
    assert abs(observed_order(hs, local) - (q + 1)) < 0.3
    assert ratios[-1] < 0.05  # err is the embedded solution's error, to leading order


@pytest.mark.parametrize("name", ADAPTIVE)
def test_solve_accepts_a_step_by_the_tableaus_error_estimate(name):
    """With rtol = 0 a step is accepted iff RMS(err) ≤ atol: `solve` estimates the error
    with the tableau's weights (one step of size h, just above and below the threshold)."""
    y0 = np.array([1.0, 0.5, -0.3])
    mt = torch.tensor(M)
    h = 0.1
    _, err, _ = one_step(name, y0, h)
    rms = float(np.sqrt(np.mean(err**2)))
    accepted = []
    for atol in (1.001 * rms, 0.999 * rms):
        sol = solve(lambda t, y: y @ mt.T, torch.tensor(y0)[None], [0.0, h], method=name,
                    rtol=0.0, atol=atol, dt0=h, max_steps=1)
        accepted.append(int(sol.stats["n_accepted"][0]))
    assert accepted == [1, 0]


@pytest.mark.parametrize("name", METHODS)
def test_interpolant_has_its_local_order(name):
    """One step's dense output y(θh) has local error h^(q+1), q the interpolant's order."""
    y0 = np.array([1.0, 0.5, -0.3])
    hs, errors = [0.4, 0.2, 0.1, 0.05], []
    for h in hs:
        _, _, dense = one_step(name, y0, h)
        errors.append(max(np.abs(dense(th) - expm(M * th * h) @ y0).max()
                          for th in (0.3, 0.5, 0.7)))
    order = observed_order(hs, errors)
    assert abs(order - (METHODS[name].dense_order + 1)) < 0.3, (order, errors)


@pytest.mark.parametrize("name", ADAPTIVE)
def test_dense_output_error_has_order_at_least_4(name):
    """Outputs between steps come from the interpolant: error ~ h^5 locally, ≥ h^4 globally."""
    y0 = torch.tensor([[1.0, 0.5, -0.3]], dtype=torch.float64)
    mt = torch.tensor(M)
    ts = torch.linspace(0.0, 2.0, 41, dtype=torch.float64)
    exact = linear_exact(y0[0].numpy(), ts.numpy())
    hs, errors = [0.4, 0.2, 0.1, 0.05], []
    for h in hs:
        # Steps fixed at h via the stop grid (tstops), outputs in between interpolated.
        stops = torch.arange(h, 2.0 + 1e-9, h, dtype=torch.float64)
        sol = solve(lambda t, y: y @ mt.T, y0, ts, method=name, rtol=1e3, atol=1e3, dt0=h,
                    tstops=stops)
        errors.append(np.abs(sol.ys[0].numpy() - exact).max())
    assert observed_order(hs, errors) > METHODS[name].dense_order - 0.2, errors


def test_rk4_takes_fixed_steps_only():
    f = lambda t, y: -y  # noqa: E731
    y0 = torch.ones(1, 1, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"rk4.*no error estimate.*fixed_dt"):
        solve(f, y0, [0.0, 1.0], method="rk4")
    with pytest.raises(ValueError, match=r"unknown solver method 'rk5'.*tsit5, dopri5, rk4"):
        solve(f, y0, [0.0, 1.0], method="rk5")
    sol = solve(f, y0, [0.0, 0.25, 1.0], method="rk4", fixed_dt=0.1)
    # 11 steps (as `test_fixed_dt_steps_align_with_output_times`), 4 new evaluations each.
    assert int(sol.stats["n_steps"][0]) == 11 and int(sol.stats["n_f_evals"][0]) == 1 + 4 * 11


# ----------------------------------------------------------------------------- accuracy vs scipy


def lorenz(t, y):
    x, yy, z = y.unbind(-1)
    return torch.stack((10 * (yy - x), x * (28 - z) - yy, x * yy - 8 / 3 * z), -1)


def two_body(t, y):
    r = y[..., :2]
    rn = r.norm(dim=-1, keepdim=True)
    return torch.cat((y[..., 2:], -r / rn**3), -1)


def van_der_pol(t, y):
    x, v = y.unbind(-1)
    return torch.stack((v, (1 - x**2) * v - x), -1)


def numpy_version(f):
    return lambda t, y: f(t, torch.tensor(y)[None])[0].numpy()


PROBLEMS = {
    "lorenz": (lorenz, [[1.0, 1.0, 1.0], [-2.0, 3.0, 20.0]], 2.0),
    "two_body": (two_body, [[1.0, 0.0, 0.0, 1.2], [0.8, 0.0, 0.0, 1.0]], 6.0),
    "van_der_pol": (van_der_pol, [[2.0, 0.0], [0.5, -1.0]], 8.0),
}


@pytest.mark.parametrize(("method", "name"), [
    *(("tsit5", name) for name in sorted(PROBLEMS)), ("dopri5", "lorenz"), ("dopri5", "two_body")])
def test_matches_scipy_dop853_at_tight_tolerance(method, name):
    f, y0s, t_end = PROBLEMS[name]
    ts = torch.linspace(0.0, t_end, 33, dtype=torch.float64)
    y0 = torch.tensor(y0s, dtype=torch.float64)
    sol = solve(f, y0, ts, method=method, rtol=1e-10, atol=1e-12)
    assert bool(sol.success.all())
    for i, y in enumerate(y0s):
        ref = solve_ivp(numpy_version(f), (0.0, t_end), y, method="DOP853", t_eval=ts.numpy(),
                        rtol=1e-13, atol=1e-14).y.T
        rel = np.linalg.norm(sol.ys[i].numpy() - ref) / np.linalg.norm(ref)
        assert rel < 1e-7, (name, i, rel)


def test_float32_solve_is_accurate_to_its_tolerance():
    ts = torch.linspace(0.0, 6.0, 13, dtype=torch.float64)
    y0 = torch.tensor([[2.0, 0.0]], dtype=torch.float32)
    sol = solve(van_der_pol, y0, ts, rtol=1e-5, atol=1e-6)
    assert sol.ys.dtype == torch.float32
    ref = solve_ivp(numpy_version(van_der_pol), (0, 6), [2.0, 0.0], method="DOP853",
                    t_eval=ts.numpy(), rtol=1e-12, atol=1e-12).y.T
    assert np.abs(sol.ys[0].double().numpy() - ref).max() < 1e-3


@pytest.mark.parametrize("name", sorted(PROBLEMS))
def test_integral_controller_meets_loose_tolerances(name):
    """At training tolerances both controllers' solutions are accurate (scipy DOP853 referee),
    and on these hard problems, where steps sit at the error bound, they take as many steps
    as each other to within 10%."""
    f, y0s, t_end = PROBLEMS[name]
    ts = torch.linspace(0.0, t_end, 33, dtype=torch.float64)
    y0 = torch.tensor(y0s, dtype=torch.float64)
    steps = {}
    for kind in ("pi", "i"):
        sol = solve(f, y0, ts, rtol=1e-4, atol=1e-4, controller=kind)
        assert bool(sol.success.all())
        steps[kind] = int(sol.stats["n_steps"].sum())
        for i, y in enumerate(y0s):
            ref = solve_ivp(numpy_version(f), (0.0, t_end), y, method="DOP853",
                            t_eval=ts.numpy(), rtol=1e-12, atol=1e-12).y.T
            rel = np.linalg.norm(sol.ys[i].numpy() - ref) / np.linalg.norm(ref)
            assert rel < 3e-2, (name, kind, i, rel)
    assert abs(steps["i"] - steps["pi"]) <= 0.1 * steps["pi"], steps
    with pytest.raises(ValueError, match="controller"):
        solve(f, y0, ts, controller="pid")


def test_a_controller_object_carries_its_tolerances_and_coefficients():
    """`solve(controller=PIController(rtol=..., atol=...))`, as diffrax and torchode take
    one: it is the named controller with those tolerances (the same steps), its tolerances
    reach the error test (tighter ones take more steps and land closer to e^{−t}), and so
    do its coefficients (a smaller safety factor shrinks every proposal: more steps)."""
    y0 = torch.tensor([[1.0], [3.0]], dtype=torch.float64)
    ts = torch.linspace(0.0, 2.0, 5, dtype=torch.float64)
    exact = y0 * torch.exp(-ts)  # (B, T)
    errors, steps = [], []
    for rtol in (1e-4, 1e-8):
        sol = solve(lambda t, y: -y, y0, ts, controller=PIController(rtol=rtol, atol=rtol))
        named = solve(lambda t, y: -y, y0, ts, controller="pi", rtol=rtol, atol=rtol)
        assert torch.equal(sol.ys, named.ys)
        assert torch.equal(sol.stats["n_steps"], named.stats["n_steps"])
        error = float((sol.ys[..., 0] - exact).abs().max())
        assert error < 10 * rtol
        errors.append(error)
        steps.append(int(sol.stats["n_steps"].sum()))
    assert steps[1] > steps[0] and errors[1] < errors[0]
    careful = solve(lambda t, y: -y, y0, ts, controller=PIController(rtol=1e-8, atol=1e-8,
                                                                       safety=0.5))
    assert int(careful.stats["n_steps"].sum()) > steps[1]
    with pytest.raises(ValueError, match="controller object carries rtol and atol"):
        solve(lambda t, y: -y, y0, ts, controller=IController(), rtol=1e-3)


def test_integral_controller_takes_fewer_steps_where_steps_are_far_below_the_bound():
    """A smooth solution over a short horizon (y' = −y to t = 2.5, like a training rollout):
    PI's history term r_prev^β₂ < 1 slows growth after very accurate steps; I does not."""
    ts = torch.linspace(0.0, 2.5, 51, dtype=torch.float64)
    y0 = torch.tensor([[1.0, 0.5]], dtype=torch.float64)
    n = {}
    for kind in ("pi", "i"):
        sol = solve(lambda t, y: -y, y0, ts, rtol=1e-4, atol=1e-4, controller=kind)
        n[kind] = int(sol.stats["n_steps"].sum())
        exact = y0[:, None] * torch.exp(-ts)[None, :, None]
        assert float((sol.ys - exact).abs().max()) < 1e-4
    assert n["i"] < n["pi"], n


# ----------------------------------------------------------------------------- batching & status


def parametrised_rhs(mu: torch.Tensor, blow: torch.Tensor):
    """Van der Pol with per-sample μ; where blow = 1 instead x' = v + x², v' = 0 (blows up)."""

    def f(t, y):
        x, v = y.unbind(-1)
        return torch.stack((v + blow * x**2, (1 - blow) * (mu * (1 - x**2) * v - x)), -1)

    return f


def test_each_sample_in_a_batch_equals_the_sample_solved_alone():
    gen = torch.Generator().manual_seed(0)
    batch = 64
    mu = torch.rand(batch, generator=gen, dtype=torch.float64) * 2
    blow = torch.zeros(batch, dtype=torch.float64)
    blow[[3, 17, 40]] = 1.0  # these samples blow up in finite time
    y0 = torch.rand(batch, 2, generator=gen, dtype=torch.float64) * 4 - 2
    y0[[3, 17, 40], 0] = 3.0
    ts = torch.linspace(0.0, 5.0, 26, dtype=torch.float64)
    sol = solve(parametrised_rhs(mu, blow), y0, ts, rtol=1e-8, atol=1e-10)
    assert set(sol.status[[3, 17, 40]].tolist()) <= {Status.NON_FINITE, Status.DT_UNDERFLOW}
    assert bool((sol.status[blow == 0] == Status.SUCCESS).all())
    # Solved alone: one blow-up (the other two fail the same way, from x0 = 3) and, of the
    # others, the first and those with the fewest and the most steps.
    steps = sol.stats["n_steps"].double()
    fewest = int(torch.where(blow == 0, steps, math.inf).argmin())
    most = int(torch.where(blow == 0, steps, -math.inf).argmax())
    for i in (3, 0, fewest, most):
        alone = solve(parametrised_rhs(mu[i : i + 1], blow[i : i + 1]), y0[i : i + 1], ts,
                      rtol=1e-8, atol=1e-10)
        assert alone.status[0] == sol.status[i]
        assert alone.stats["n_steps"][0] == sol.stats["n_steps"][i]
        # A sample's arithmetic does not depend on its neighbours, but its rounding may
        # (a vectorised against a scalar `pow`: 1.2% of float64 inputs differ in the last
        # bit on an AMD EPYC). The growth of a deviation: at most e^{μ·t}-ish on the
        # oscillators, and (x(t)/x(s))² on the blow-up x' = v + x² (x0 = 3): bounded by
        # the sample's largest |x| over its start's, times that |x|.
        size = sol.ys[i].abs().nan_to_num(0.0)
        growth = 1 + size.amax() / y0[i].abs().amax()
        bound = rounding_apart(sol.stats["n_steps"][i], (1 + size) * growth)
        assert torch.equal(alone.ys[0].isnan(), sol.ys[i].isnan())
        assert bool(((alone.ys[0] - sol.ys[i]).abs().nan_to_num(0.0) <= bound).all())


def test_blow_up_is_marked_and_other_samples_succeed():
    f = lambda t, y: y**2  # noqa: E731  y(0)=1 → 1/(1−t), singular at t = 1
    y0 = torch.tensor([[1.0], [0.1], [-1.0]], dtype=torch.float64)
    ts = torch.linspace(0.0, 2.0, 21, dtype=torch.float64)
    sol = solve(f, y0, ts)
    assert Status(int(sol.status[0])) in (Status.NON_FINITE, Status.DT_UNDERFLOW)
    assert sol.status[1:].tolist() == [Status.SUCCESS, Status.SUCCESS]
    exact = y0[1:, 0, None] / (1 - y0[1:, 0, None] * ts)
    torch.testing.assert_close(sol.ys[1:, :, 0], exact, rtol=1e-5, atol=1e-7)
    # The failed sample keeps its solution up to the failure; later outputs are NaN.
    before = ts < 0.95
    torch.testing.assert_close(sol.ys[0, before, 0], 1 / (1 - ts[before]), rtol=1e-4, atol=0)
    assert bool(torch.isnan(sol.ys[0, ts > 1.0, 0]).all())
    assert Status.DT_UNDERFLOW.message and "max_steps" in Status.MAX_STEPS.message


def test_a_blow_up_is_marked_once_steps_stop_advancing_time():
    """Near the singularity of y' = y² every step is accepted while the step size falls below
    the clock's resolution; the sample must fail there, not keep stepping on the spot."""
    y0 = torch.ones(1, 1, dtype=torch.float64)
    sol = solve(lambda t, y: y**2, y0, [0.0, 2.0], rtol=1e-8, atol=1e-10)
    assert sol.status.tolist() == [Status.DT_UNDERFLOW]
    assert int(sol.stats["n_steps"][0]) < 600  # 3946 steps when only rejections were checked


def test_max_steps_marks_only_the_samples_that_need_more():
    rate = torch.tensor([1.0, 2000.0], dtype=torch.float64)  # the second is stiff
    y0 = torch.ones(2, 1, dtype=torch.float64)
    sol = solve(lambda t, y: -rate[:, None] * y, y0, [0.0, 1.0, 2.0], max_steps=50)
    assert sol.status.tolist() == [Status.SUCCESS, Status.MAX_STEPS]
    assert sol.stats["n_steps"][1] == 50
    assert sol.ys[0, -1, 0].item() == pytest.approx(math.exp(-2.0), rel=1e-5)


def test_non_finite_initial_state_is_marked():
    y0 = torch.tensor([[1.0], [math.nan]], dtype=torch.float64)
    sol = solve(lambda t, y: -y, y0, [0.0, 1.0])
    assert sol.status.tolist() == [Status.SUCCESS, Status.NON_FINITE]
    sol = solve(lambda t, y: -y, y0, [0.0, 1.0], fixed_dt=0.1)
    assert sol.status.tolist() == [Status.SUCCESS, Status.NON_FINITE]


def test_stats_count_function_evaluations():
    calls = []

    def f(t, y):
        calls.append(1)
        return -y

    sol = solve(f, torch.ones(3, 2, dtype=torch.float64), [0.0, 1.0])
    st = sol.stats
    assert torch.equal(st["n_steps"], st["n_accepted"] + st["n_rejected"])
    assert int(st["n_f_evals"].max()) == len(calls) == 2 + 6 * int(st["n_steps"].max())


# ----------------------------------------------------------------------------- stops, fixed steps


def test_tstops_let_a_zero_order_hold_input_be_integrated_exactly():
    switch = 0.537
    u = lambda t: torch.where(t < switch, 1.0, -2.0)  # noqa: E731
    f = lambda t, y: u(t)[:, None].to(y.dtype).expand_as(y)  # noqa: E731
    ts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    exact = torch.where(ts < switch, ts, switch - 2 * (ts - switch))
    y0 = torch.zeros(1, 1, dtype=torch.float64)
    with_stop = solve(f, y0, ts, tstops=[switch], rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(with_stop.ys[0, :, 0], exact, rtol=0, atol=1e-12)
    fixed = solve(f, y0, ts, tstops=[switch], fixed_dt=0.3)
    torch.testing.assert_close(fixed.ys[0, :, 0], exact, rtol=0, atol=1e-12)


def test_fixed_dt_steps_align_with_output_times():
    calls = []

    def f(t, y):
        calls.append(t[0].item())
        return -y

    ts = [0.0, 0.25, 1.0]
    sol = solve(f, torch.ones(1, 1, dtype=torch.float64), ts, fixed_dt=0.1)
    # [0, 0.25] in 3 steps, [0.25, 1] in 8 steps: 11 steps, 6 new evaluations each.
    assert int(sol.stats["n_steps"][0]) == 11 and len(calls) == 1 + 6 * 11
    torch.testing.assert_close(sol.ys[0, :, 0], torch.exp(-torch.tensor(ts, dtype=torch.float64)),
                               rtol=1e-8, atol=0)


def test_input_validation():
    y0 = torch.ones(2, 1)
    with pytest.raises(ValueError, match="strictly increasing"):
        solve(lambda t, y: y, y0, [0.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="float32 or float64"):
        solve(lambda t, y: y, torch.ones(2, 1, dtype=torch.int64), [0.0, 1.0])
    sol = solve(lambda t, y: y, y0, [0.5])
    assert sol.ys.shape == (2, 1, 1)


# ----------------------------------------------------------------------------- gradients


def make_problem(theta):
    def f(t, y):
        return -theta[0] * y + theta[1] * torch.sin(y) * y.flip(-1)

    return f


@pytest.mark.parametrize("mode", ["adaptive", "fixed"])
def test_gradcheck_through_the_solve(mode):
    ts = torch.tensor([0.0, 0.2, 0.5], dtype=torch.float64)
    options = {"rtol": 1e-10, "atol": 1e-12} if mode == "adaptive" else {"fixed_dt": 0.05}

    def run(y0, theta):
        return solve(make_problem(theta), y0, ts, **options).ys

    y0 = torch.tensor([[0.3, -0.7], [1.1, 0.2]], dtype=torch.float64, requires_grad=True)
    theta = torch.tensor([0.8, 0.5], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (y0, theta), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradients_are_finite_when_a_sample_in_the_batch_fails():
    theta = torch.tensor(1.0, dtype=torch.float64, requires_grad=True)
    f = lambda t, y: theta * y**2  # noqa: E731
    y0 = torch.tensor([[0.1], [1.0]], dtype=torch.float64)
    sol = solve(f, y0, [0.0, 0.5, 2.0])
    assert sol.status.tolist()[0] == Status.SUCCESS and sol.status.tolist()[1] != Status.SUCCESS
    sol.ys[0].sum().backward()
    assert torch.isfinite(theta.grad)
    # d/dθ of y(t) = y0 / (1 − θ y0 t) at θ = 1: y0² t / (1 − y0 t)²
    want = sum(0.01 * t / (1 - 0.1 * t) ** 2 for t in (0.5, 2.0))
    assert theta.grad.item() == pytest.approx(want, rel=1e-4)


@pytest.mark.parametrize("fixed_dt", [None, 0.1])
def test_a_non_contiguous_initial_state_is_accepted(fixed_dt):
    x = torch.randn(4, 5, 2, 3, dtype=torch.float64)
    y0 = x[:, 0]  # a strided view, as a model gets it from x [B, T, N, D]
    a = solve(lambda t, y: -y, y0, [0.0, 0.5], fixed_dt=fixed_dt)
    b = solve(lambda t, y: -y, y0.contiguous(), [0.0, 0.5], fixed_dt=fixed_dt)
    torch.testing.assert_close(a.ys, b.ys, rtol=0, atol=0)


@pytest.mark.slow
def test_compiled_step_gives_the_eager_result():
    """torch.compile of the step (~10 s to compile): same steps, same answer to rounding."""
    y0 = torch.tensor([[1.0, 1.0, 1.0], [-2.0, 3.0, 20.0]], dtype=torch.float64)
    ts = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)
    eager = solve(lorenz, y0, ts, rtol=1e-8, atol=1e-10)
    compiled = solve(lorenz, y0, ts, rtol=1e-8, atol=1e-10, compile=True)
    assert torch.equal(eager.stats["n_steps"], compiled.stats["n_steps"])
    torch.testing.assert_close(compiled.ys, eager.ys, rtol=1e-9, atol=1e-9)
