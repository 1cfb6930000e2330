"""`generate` and the `mpnode generate` / `mpnode info` commands, at tiny sizes.

Paper-scale generation is the benchmark's job (`bench/generate.py`); here every preset is
only resolved.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data import hdf5_write, solve_rounds
from mpnode_cli.data.generate import GenerateError, generate, resolve_generate_config
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.data.presets import PRESETS, get_preset
from mpnode_cli.solver import Status
from mpnode_cli.systems import get_system

TINY = {"trajectories": 6, "t_end": 0.3, "dt": 0.1}
# One small, valid configuration per system (CLI arguments).
SYSTEM_ARGS = {
    "pendulum": ["pendulum", "--nodes", "3"],
    "lorenz": ["lorenz", "--nodes", "3", "--coupling", "1.0"],
    "gene": ["gene", "--grid", "3", "--topology", "er", "--init", "hotspot", "--graphs", "2"],
    "kuramoto": ["kuramoto", "--nodes", "7", "--topology", "ws", "-p", "K=0.5"],
}
TINY_ARGS = ["--trajectories", "6", "--t-end", "0.3", "--dt", "0.1"]


def _config(tmp_path, name="d.h5", **fields) -> GenerateConfig:
    return GenerateConfig(
        **{"system": "lorenz", "nodes": 3, **TINY, "out": tmp_path / name, **fields}
    )


# ----- the library --------------------------------------------------------------------------


def test_same_seed_is_bit_identical_and_seeds_differ(tmp_path):
    a = read_dataset(generate(_config(tmp_path, "a.h5", dtype="float64")).path)
    b = read_dataset(generate(_config(tmp_path, "b.h5", dtype="float64", chunk_size=4)).path)
    c = read_dataset(generate(_config(tmp_path, "c.h5", dtype="float64", seed=1)).path)
    again = read_dataset(generate(_config(tmp_path, "a2.h5", dtype="float64")).path)
    assert a.states.tobytes() == again.states.tobytes()  # same config: bit-identical
    # Another chunk size changes only the rounding of the batched matmul.
    np.testing.assert_allclose(a.states, b.states, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(a.split, b.split)
    assert not np.allclose(a.states, c.states)
    # The graph seed, not the trajectory seed, fixes the system (lorenz coupling).
    np.testing.assert_array_equal(a.params["coupling"], c.params["coupling"])


def test_file_contents(tmp_path):
    config = _config(tmp_path, trajectories=10, graphs=1, split=(0.6, 0.2, 0.2))
    summary = generate(config)
    ds = read_dataset(summary.path)
    assert ds.states.shape == (10, 4, 3, 3) and ds.states.dtype == np.float32
    np.testing.assert_allclose(ds.time, [0.0, 0.1, 0.2, 0.3])
    assert summary.split_counts == (6, 2, 2) and np.bincount(ds.split).tolist() == [6, 2, 2]
    assert (ds.solver_status == Status.SUCCESS).all() and (ds.solver_n_f_evals > 0).all()
    assert summary.n_f_evals == int(ds.solver_n_f_evals.sum())
    assert ds.params["coupling"].shape == (1, 9, 9)
    np.testing.assert_allclose(np.linalg.norm(ds.params["coupling"][0]), 0.01)
    assert ds.scalar_params == pytest.approx({"sigma": 10, "rho": 28, "beta": 8 / 3})
    assert ds.state_names == ("x", "y", "z") and ds.seed == 0
    # The stored config is the resolved one, and builds the same config again.
    assert GenerateConfig(**ds.config) == resolve_generate_config(config)
    # Initial states are the sampler's: U(-1, 1).
    assert np.abs(ds.states[:, 0]).max() <= 1.0


def test_graphs_and_trajectories_spread_evenly(tmp_path):
    config = _config(tmp_path, system="gene", nodes=None, grid=3, topology="er", graphs=3,
                     trajectories=7)  # fmt: skip
    ds = read_dataset(generate(config).path)
    assert ds.adjacency.shape == (3, 9, 9) and ds.num_nodes == 9
    assert np.bincount(ds.graph_index).tolist() == [3, 2, 2]
    assert not np.array_equal(ds.adjacency[0], ds.adjacency[1])  # seeds graph_seed + g
    expected = get_system("gene").graph("er", 9, 0 + 2)
    np.testing.assert_array_equal(ds.adjacency[2], expected)


@pytest.mark.parametrize("chunk_size", [2, 1024])  # chunks within one graph, and across
def test_each_trajectory_ran_on_its_own_graph(tmp_path, chunk_size):
    """Gene dynamics, dx_i/dt = -b x_i^f + sum_j A_ij x_j^h / (1 + x_j^h) (the paper, Eq. 9),
    re-solved with scipy on the graph each trajectory is stored with."""
    from scipy.integrate import solve_ivp

    config = _config(tmp_path, system="gene", nodes=None, grid=3, topology="er", graphs=3,
                     trajectories=7, t_end=1.0, chunk_size=chunk_size)
    ds = read_dataset(generate(config).path)
    p = ds.scalar_params
    for k in range(len(ds.states)):
        a = ds.adjacency[ds.graph_index[k]].astype(np.float64)

        def f(_t, x, a=a):
            return -p["b"] * x ** p["f"] + a @ (x ** p["h"] / (1.0 + x ** p["h"]))

        ref = solve_ivp(f, (0.0, 1.0), ds.states[k, 0, :, 0].astype(np.float64),
                        t_eval=ds.time, method="DOP853", rtol=1e-10, atol=1e-10).y.T
        np.testing.assert_allclose(ds.states[k, :, :, 0], ref, rtol=1e-5, atol=1e-6)


def test_edge_list_graph(tmp_path):
    edges = tmp_path / "ring.txt"
    edges.write_text("# a ring of 5\n0 1\n1 2\n2 3\n3 4\n4 0\n")
    config = _config(tmp_path, system="kuramoto", nodes=None, edge_list=edges, graphs=2)
    ds = read_dataset(generate(config).path)
    assert ds.config["topology"] == "edgelist" and ds.num_nodes == 5
    np.testing.assert_array_equal(ds.adjacency[0], ds.adjacency[1])
    assert ds.adjacency[0].sum() == 10 and ds.adjacency[0, 0, 4] == 1
    assert not np.array_equal(ds.params["omega"][0], ds.params["omega"][1])  # ω per graph
    with pytest.raises(ValueError, match="edge list has 5"):
        resolve_generate_config(_config(tmp_path, system="kuramoto", nodes=6, edge_list=edges))


def test_kuramoto_ba_and_er_share_omega_unless_omega_seed_is_given(tmp_path):
    """One graph seed, one ω: the BA and ER presets differ only in the adjacency. An
    `-p omega_seed=S` dataset draws other frequencies; the default leaves data as it was."""
    def omega(name, *args):
        out = tmp_path / f"{len(list(tmp_path.iterdir()))}.h5"
        result = runner.invoke(app, ["generate", "--preset", name, *TINY_ARGS, *args,
                                     "--out", str(out)])
        assert result.exit_code == 0, result.output
        return read_dataset(out).params["omega"]

    ba, er = omega("kuramoto10-ba"), omega("kuramoto10-er")
    np.testing.assert_array_equal(ba, er)
    np.testing.assert_array_equal(ba[0], np.random.default_rng([0, 0]).standard_normal(3))
    other = omega("kuramoto10-er", "-p", "omega_seed=1")
    assert not np.allclose(other, ba)
    np.testing.assert_array_equal(other, omega("kuramoto10-er", "-p", "omega_seed=1"))

def test_rejected_and_failed_trajectories_are_redrawn(tmp_path):
    # The appendix's wide box makes about one pendulum trajectory in five singular.
    config = _config(tmp_path, system="pendulum", nodes=2, trajectories=20, t_end=2.0,
                     params={"ic_range": "paper"}, dtype="float64")  # fmt: skip
    summary = generate(config)
    ds = read_dataset(summary.path)
    assert summary.failed + summary.rejected > 0
    assert ds.extra_attrs["n_rejected"] == summary.rejected
    assert ds.extra_attrs["n_failed"] == summary.failed
    assert (ds.solver_status == 0).all() and np.isfinite(ds.states).all()
    assert not get_system("pendulum").reject(ds.states).any()


def test_progress_reports_every_chunk(tmp_path):
    calls = []
    generate(_config(tmp_path, trajectories=5, chunk_size=2), progress=lambda *a: calls.append(a))
    # Three chunks of at most 2 (a slow chunk may also report within itself).
    done = [c[0] for c in calls]
    assert calls[0] == (0, 5) and calls[-1] == (5, 5) and {2, 4} <= set(done)
    assert done == sorted(done) and {c[1] for c in calls} == {5}


def test_existing_file_is_kept_without_overwrite(tmp_path):
    path = generate(_config(tmp_path)).path
    before = path.read_bytes()
    with pytest.raises(FileExistsError, match="--force"):
        generate(_config(tmp_path, seed=3))
    assert path.read_bytes() == before
    generate(_config(tmp_path, seed=3), overwrite=True)
    assert read_dataset(path).seed == 3


def test_interrupted_generation_leaves_nothing(tmp_path, monkeypatch):
    def interrupted(f, ds, *check):
        f.create_dataset("states", data=ds.states)
        raise KeyboardInterrupt

    monkeypatch.setattr(hdf5_write, "_write", interrupted)
    with pytest.raises(KeyboardInterrupt):
        generate(_config(tmp_path))
    assert list(tmp_path.iterdir()) == []


def test_systematic_failure_is_an_error(tmp_path, monkeypatch):
    real = solve_rounds.solve_chunk

    def always_underflow(*args):
        sol = real(*args)
        sol.status.fill_(Status.DT_UNDERFLOW)
        return sol

    monkeypatch.setattr(solve_rounds, "solve_chunk", always_underflow)
    with pytest.raises(GenerateError, match=r"every trajectory failed.*DT_UNDERFLOW"):
        generate(_config(tmp_path, trajectories=12))
    assert list(tmp_path.iterdir()) == []


def test_endless_rejection_gives_up(tmp_path, monkeypatch):
    monkeypatch.setattr(solve_rounds, "MAX_REDRAW_ROUNDS", 2)
    monkeypatch.setattr(type(get_system("lorenz")), "reject", lambda self, s: np.ones(len(s), bool))
    with pytest.raises(GenerateError, match="still failed after 2 redraws"):
        generate(_config(tmp_path))


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"system": "nope"}, "unknown system 'nope'"),
        ({"topology": "ba"}, "no topology 'ba'"),
        ({"system": "kuramoto", "nodes": 4}, "needs more than 5 nodes"),
        ({"system": "gene", "nodes": 5, "params": {"init": "hotspot"}}, "square grid"),
        ({"params": {"omega": 1.0}}, "unknown parameter 'omega'"),
        ({"edge_list": "missing.txt", "nodes": None}, "cannot read edge list"),
    ],
)
def test_resolve_rejects_what_cannot_be_built(tmp_path, fields, message):
    with pytest.raises(ValueError, match=message):
        resolve_generate_config(_config(tmp_path, **fields))


def test_resolve_fills_system_defaults():
    config = resolve_generate_config(GenerateConfig(system="lorenz"))
    assert (config.nodes, config.topology, config.trajectories) == (3, "complete", 1000)
    assert (config.t_end, config.dt, config.num_steps) == (2.5, 0.05, 50)
    assert str(config.out) == "datasets/lorenz-n3-complete-s0.h5"
    assert resolve_generate_config(GenerateConfig(system="gene", grid=8)).nodes == 64


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_resolves(name):
    config = resolve_generate_config(GenerateConfig(**get_preset(name)))
    assert config.trajectories >= 200 and config.num_steps >= 50


def test_presets_match_the_paper():
    assert set(PRESETS) == {
        "pendulum", "lorenz3", "lorenz7", "lorenz10", "lorenz10-high", "lorenz10-long",
        *(f"gene-{t}-{s}x{s}" for t in ("ba", "er", "ws") for s in (4, 8)),
        *(f"kuramoto10-{t}" for t in ("ba", "er", "ws")), "quad3", "quad6",
    }  # fmt: skip
    resolved = {name: resolve_generate_config(GenerateConfig(**get_preset(name)))
                for name in PRESETS}
    assert (resolved["pendulum"].trajectories, resolved["pendulum"].num_steps) == (500, 100)
    assert resolved["lorenz10-high"].params == {"coupling": 1.0}
    assert resolved["lorenz10-long"].num_steps == 200
    assert resolved["gene-ws-8x8"].nodes == 64 and resolved["gene-ba-4x4"].graphs == 5
    assert resolved["kuramoto10-er"].topology == "er" and resolved["kuramoto10-er"].nodes == 10


# ----- the commands -------------------------------------------------------------------------

runner = CliRunner()


@pytest.mark.parametrize("system", sorted(SYSTEM_ARGS))
def test_cli_generates_every_system(tmp_path, monkeypatch, system):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["generate", *SYSTEM_ARGS[system], *TINY_ARGS, "--seed", "4"])
    assert result.exit_code == 0, result.output
    files = list((tmp_path / "datasets").iterdir())
    assert len(files) == 1 and files[0].name.startswith(f"{system}-n") and "-s4" in files[0].name
    assert "RHS evaluations" in result.stdout and "failed / rejected" in result.stdout
    ds = read_dataset(files[0])
    assert ds.system == system and ds.num_trajectories == 6 and ds.seed == 4

    info = runner.invoke(app, ["info", str(files[0])])
    assert info.exit_code == 0, info.output
    assert system in info.stdout and "mpnode-dataset v3" in info.stdout


def test_cli_preset_config_file_and_options_layer(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text("trajectories = 4\nt_end = 0.2\n[params]\ncoupling = 0.5\n")
    out = tmp_path / "x.h5"
    result = runner.invoke(
        app, ["generate", "--preset", "lorenz7", "--config", str(toml), "--dt", "0.1",
              "--out", str(out)],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    config = read_dataset(out).config
    assert (config["nodes"], config["trajectories"], config["t_end"], config["dt"]) == (
        7, 4, 0.2, 0.1,
    )  # fmt: skip
    assert config["params"] == {"coupling": 0.5}
    # A dataset's stored config regenerates it.
    stored = tmp_path / "stored.json"
    stored.write_text(json.dumps({**config, "out": str(tmp_path / "y.h5")}))
    assert runner.invoke(app, ["generate", "--config", str(stored)]).exit_code == 0
    assert read_dataset(tmp_path / "y.h5").states.tobytes() == read_dataset(out).states.tobytes()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["nope"], "unknown system 'nope'"),
        (["lorenz", "--trajectories", "-5"], "trajectories"),
        (["lorenz", "--dt", "1", "--t-end", "0.5"], "dt (1) is larger than t_end (0.5)"),
        (["lorenz", "--split", "0.5,0.6"], "split"),
        (["lorenz", "--split", "0.5,0.6,0.1"], "sum to 1"),
        (["gene", "--coupling", "1"], "unknown parameter 'coupling'"),
        (["lorenz", "--topology", "ring"], "no topology 'ring'"),
        (["--preset", "lorenz99"], "unknown preset"),
        (["--preset", "lorenz3", "gene"], "disagrees"),
        (["lorenz", "-p", "sigma"], "NAME=VALUE"),
        (["lorenz", "--config", "missing.toml"], "cannot read config file"),
        (["--trajectories", "3"], "give a SYSTEM"),
    ],
)
def test_cli_bad_input_is_one_line_and_exit_2(tmp_path, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["generate", *args])
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: ") and message in lines[0], lines
    assert not (tmp_path / "datasets").exists()


def test_cli_refuses_existing_file_without_force(tmp_path):
    out = tmp_path / "d.h5"
    args = ["generate", "lorenz", *TINY_ARGS, "--out", str(out)]
    assert runner.invoke(app, args).exit_code == 0
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert result.stderr.strip() == f"Error: {out} already exists (use --force to overwrite)"
    assert runner.invoke(app, [*args, "--force"]).exit_code == 0


def test_cli_ctrl_c_writes_nothing(tmp_path, monkeypatch):
    def interrupted(f, ds, *check):
        raise KeyboardInterrupt

    monkeypatch.setattr(hdf5_write, "_write", interrupted)
    out = tmp_path / "d.h5"
    result = runner.invoke(app, ["generate", "lorenz", *TINY_ARGS, "--out", str(out)])
    assert result.exit_code == 130 and "nothing written" in result.stderr
    assert list(tmp_path.iterdir()) == []


def test_cli_info_bad_files(tmp_path):
    (tmp_path / "text.h5").write_text("no")
    for path, message in [("missing.h5", "no such dataset file"), ("text.h5", "not an HDF5")]:
        result = runner.invoke(app, ["info", str(tmp_path / path)])
        assert result.exit_code == 2 and message in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1


def test_help_does_not_import_torch_or_h5py():
    code = "import sys, mpnode_cli.cli.app; print(sorted({'torch', 'h5py'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
