"""The two systems brought in as a user's own (docs/own-systems.md): FitzHugh–Nagumo
neurons on Barabási–Albert graphs through `--system-file`, and swing-equation power grids
(bench/power_grid.py) through `mpnode import`. Their data are checked against the
equations, written again here, and against scipy."""

from __future__ import annotations

import importlib.util
import json
import sys

import numpy as np
import pytest
from conftest import ROOT, fhn_reference
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.data.hdf5 import read_dataset

EXAMPLE = ROOT / "examples" / "fitzhugh_nagumo.py"


def _load_power_grid():
    """bench/power_grid.py as a module (bench/ is scripts, not a package)."""
    spec = importlib.util.spec_from_file_location("power_grid", ROOT / "bench" / "power_grid.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["power_grid"] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


power_grid = _load_power_grid()


def swing(states: np.ndarray, power: np.ndarray, a_graph: np.ndarray, gamma: float,
          coupling: float) -> np.ndarray:
    """d/dt of `states` `[T, N, 2]` (θ, ω) by the swing equation (Filatrella et al. 2008),
    with injections `power` `[N]` on the graph `a_graph` `[N, N]`: `[T, N, 2]`."""
    theta, omega = states[..., 0], states[..., 1]  # [T, N]
    difference = theta[:, None, :] - theta[:, :, None]  # [T, N, N]: θ_j − θ_i at [i, j]
    pull = (a_graph * np.sin(difference)).sum(axis=-1)  # [T, N]
    return np.stack([omega, power - gamma * omega + coupling * pull], axis=-1)


@pytest.fixture(scope="module")
def grid(tmp_path_factory):
    """A small power-grid dataset on two graphs, sampled finely, with its imported arrays."""
    root = tmp_path_factory.mktemp("grid")
    params = power_grid.SwingParams(t_end=1.0, dt=0.01)
    out = power_grid.make_dataset(root / "grid.h5", nodes=8, trajectories=4, seed=3,
                                  graph_seed=5, graphs=2, params=params, dtype="float64",
                                  work_dir=root / "arrays")
    return read_dataset(out), root / "arrays", params


def test_power_grid_data_satisfy_the_swing_equation(grid):
    ds, _, params = grid
    dt = params.dt
    # Five-point central differences, whose error dt⁴/30 · |x⁽⁵⁾| is about 1e-6 here; a
    # γ or K 5 % off misses the tolerance by four orders of magnitude.
    x = ds.states  # [K, T, N, 2]
    derivative = (x[:, :-4] - 8 * x[:, 1:-3] + 8 * x[:, 3:-1] - x[:, 4:]) / (12 * dt)
    for k in range(len(x)):
        power = ds.controls[k, 0, :, 0]  # [N]
        a_graph = ds.adjacency[ds.graph_index[k]].astype(np.float64)
        expected = swing(x[k, 2:-2], power, a_graph, params.gamma, params.coupling)
        np.testing.assert_allclose(derivative[k], expected, atol=1e-5)
        assert np.abs(expected[..., 1]).max() > 0.5  # the check is not against zeros


def test_power_grid_import_keeps_the_arrays(grid):
    ds, arrays, params = grid
    with np.load(arrays / "states.npz") as written:
        np.testing.assert_array_equal(ds.states, written["states"])
        np.testing.assert_array_equal(ds.time, written["time"])
    controls = np.load(arrays / "controls.npy")
    np.testing.assert_array_equal(ds.controls, controls)
    np.testing.assert_array_equal(ds.adjacency[ds.graph_index], np.load(arrays / "adjacency.npy"))
    assert (ds.system, ds.state_names, ds.control_names) == ("custom", ("theta", "omega"), ("P",))
    assert ds.periodic_states == ("theta",)
    assert len(ds.time) == 101 and ds.dt == pytest.approx(params.dt)
    # Two Barabási–Albert graphs, the ones `mpnode generate --topology ba` builds (m = 2).
    from mpnode_cli.graphs.topologies import make_graph

    built = {make_graph("ba", 8, seed, m=2).tobytes() for seed in (5, 6)}
    assert {a.tobytes() for a in ds.adjacency} == built
    # P is held constant over time and the injections balance.
    np.testing.assert_array_equal(controls, np.broadcast_to(controls[:, :1], controls.shape))
    np.testing.assert_allclose(controls[:, 0, :, 0].sum(axis=-1), 0.0, atol=1e-12)
    record = json.loads((arrays / "power_grid.json").read_text())
    assert (record["coupling"], record["gamma"], record["graphs"]) == (2.0, 1.0, 2)


def test_power_grids_lock_within_the_default_horizon():
    """The defaults' promise: every grid synchronizes, so the raw phases stay bounded."""
    grids = power_grid.simulate(nodes=10, trajectories=6, seed=0, graph_seed=0)
    omega = grids.states[..., 1]  # [K, T, N]
    assert np.abs(omega[:, -1]).max() < 0.05  # locked at t_end
    assert np.abs(omega[:, 5]).max() > 0.5  # but not from the start
    assert np.abs(grids.states[..., 0]).max() < 4 * np.pi


def test_fhn_on_barabasi_albert_agrees_with_scipy(tmp_path):
    out = tmp_path / "fhn-ba.h5"
    result = CliRunner().invoke(app, [str(a) for a in (
        "generate", "--system-file", EXAMPLE, "--topology", "ba", "--nodes", 20, "--graphs", 2,
        "--trajectories", 4, "--t-end", 10, "--dt", 0.5, "--dtype", "float64", "--out", out)])
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    assert ds.config["topology"] == "ba" and len(ds.adjacency) == 2
    # m = 2: a connected graph whose hubs have far more than the mean degree ≈ 4.
    degree = ds.adjacency.sum(axis=-1)  # [G, N]
    assert degree.min() >= 1 and degree.max() >= 8
    for k in range(len(ds.states)):
        np.testing.assert_allclose(ds.states[k], fhn_reference(ds, k), atol=1e-6)


def test_fhn_ba_needs_more_nodes_than_m():
    result = CliRunner().invoke(app, ["generate", "--system-file", str(EXAMPLE),
                                      "--topology", "ba", "--nodes", "2"])
    assert result.exit_code == 2 and "needs more than 2 nodes" in result.output, result.output
