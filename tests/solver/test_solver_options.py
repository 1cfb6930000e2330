"""`SolverOptions`: its defaults, checks and CLI flags, and its way from the generate and
train configs (and their files, old and new) to `solve`."""

from __future__ import annotations

import inspect
import json

import h5py
import pytest
import torch
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.cli.train import train_config_from
from mpnode_cli.config.fields import generate_solver, train_solver
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.config.upgrade import (
    pin_stored_solver,
    stored_solver,
    upgrade_solver_fields,
    upgrade_train_fields,
)
from mpnode_cli.data.generate import generate
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.solver import METHODS, SolverOptions, solve
from mpnode_cli.training.checkpoint import FORMAT, read_checkpoint
from mpnode_cli.training.run import read_config

runner = CliRunner()

# A run's config as mpnode wrote it before the `solver` table: flat solver fields.
FLAT = {"rtol": 1e-3, "atol": 1e-6, "fixed_dt": None}


def test_defaults_are_solves_own():
    """Each default of `SolverOptions` is `solve`'s: its own, or for the tolerances (None
    in `solve`'s signature) the controller's."""
    from mpnode_cli.solver.controller import CONTROLLERS, StepController

    declared = inspect.signature(solve).parameters
    for name, field in SolverOptions.model_fields.items():
        if name in ("rtol", "atol"):
            assert declared[name].default is None
            assert field.default == getattr(StepController, name), name
            assert all(getattr(c, name) == field.default for c in CONTROLLERS.values())
        else:
            assert field.default == declared[name].default, name
    assert set(SolverOptions.model_fields["method"].annotation.__args__) == set(METHODS)


def test_solve_kwargs_drive_solve():
    options = SolverOptions(method="rk4", fixed_dt=0.05)
    sol = solve(lambda t, y: -y, torch.ones(1, 1, dtype=torch.float64), [0.0, 1.0],
                **options.solve_kwargs())
    assert int(sol.stats["n_steps"][0]) == 20
    assert sol.ys[0, -1, 0].item() == pytest.approx(torch.e**-1, rel=1e-7)


def test_a_method_without_error_estimate_needs_fixed_dt():
    with pytest.raises(ValueError, match=r"'rk4' has no error estimate.*give fixed_dt"):
        SolverOptions(method="rk4")
    with pytest.raises(ValueError, match="greater than 0"):
        SolverOptions(rtol=0)
    with pytest.raises(ValueError, match="Extra inputs"):
        SolverOptions(order=5)


def test_each_verb_has_its_defaults_and_a_partial_table_fills_from_them():
    assert GenerateConfig(system="lorenz").solver == generate_solver()
    assert (generate_solver().rtol, generate_solver().atol) == (1e-8, 1e-10)
    assert TrainConfig(dataset="d.h5").solver == train_solver()
    assert (train_solver().rtol, train_solver().atol) == (1e-4, 1e-4)
    config = TrainConfig(dataset="d.h5", solver={"method": "dopri5", "rtol": 1e-5})
    assert config.solver == SolverOptions(method="dopri5", rtol=1e-5, atol=1e-4, controller="i",
                                          compile="auto")
    assert GenerateConfig(system="lorenz", solver={"atol": 1e-9}).solver.rtol == 1e-8


def test_solver_options_round_trip_through_a_train_config_json():
    solver = SolverOptions(method="dopri5", rtol=1e-5, atol=1e-7, max_steps=500)
    config = TrainConfig(dataset="d.h5", solver=solver)
    fields = json.loads(config.model_dump_json())
    assert fields["solver"] == solver.model_dump()
    assert TrainConfig(**fields) == config
    assert upgrade_train_fields(fields) == fields


def test_an_old_flat_train_config_is_upgraded(tmp_path):
    fields = TrainConfig(dataset="d.h5").model_dump(mode="json")
    del fields["solver"]
    old = fields | FLAT
    # A stored config from before the controller option ran PI; a user's file gets the default.
    assert TrainConfig(**pin_stored_solver(upgrade_train_fields(old))).solver == (
        SolverOptions(rtol=1e-3, atol=1e-6, controller="pi"))
    assert TrainConfig(**upgrade_train_fields(old)).solver.controller == "i"
    (tmp_path / "config.json").write_text(json.dumps(old | {"fixed_dt": 0.02}))
    assert read_config(tmp_path).solver == SolverOptions(rtol=1e-3, atol=1e-6, fixed_dt=0.02)
    # Where a file has both, the table wins; a partial flat file keeps the verb's defaults.
    both = upgrade_solver_fields({"rtol": 1e-3, "solver": {"rtol": 1e-5}})
    assert both == {"solver": {"rtol": 1e-5}}
    assert stored_solver({"rtol": 1e-3}, train_solver) == SolverOptions(rtol=1e-3, atol=1e-4)


def test_an_old_checkpoint_is_upgraded(tmp_path):
    train_config = TrainConfig(dataset="d.h5").model_dump(mode="json")
    del train_config["solver"]
    payload = {"format": FORMAT, "format_version": 3, "model_kind": "node",
               "model_config": {"node_dim": 1, "num_nodes": 2}, "state_dict": {},
               "normalizer": {}, "train_config": train_config | FLAT | {"fixed_dt": 0.1},
               "dataset": {}, "epoch": 0}
    torch.save(payload, tmp_path / "v3.pt")
    ckpt = read_checkpoint(tmp_path / "v3.pt")  # the upgrade alone: a stub, not a model
    assert ckpt.train_config["solver"] == FLAT | {"fixed_dt": 0.1, "controller": "pi",
                                                  "compile": False}
    assert "rtol" not in ckpt.train_config
    assert stored_solver(ckpt.train_config, train_solver) == SolverOptions(
        rtol=1e-3, atol=1e-6, fixed_dt=0.1)


def test_an_old_dataset_config_is_upgraded_on_reading(tmp_path):
    config = GenerateConfig(system="lorenz", nodes=2, trajectories=2, t_end=0.1, dt=0.05,
                            solver={"method": "dopri5"}, out=tmp_path / "d.h5")
    path = generate(config).path
    stored = read_dataset(path).config
    assert stored["solver"] == SolverOptions(method="dopri5", rtol=1e-8, atol=1e-10).model_dump()
    flat = {k: v for k, v in stored.items() if k != "solver"} | {"rtol": 1e-7, "atol": 1e-9}
    with h5py.File(path, "r+") as f:
        f.attrs["config"] = json.dumps(flat)
    upgraded = read_dataset(path).config
    assert GenerateConfig(**upgraded).solver == SolverOptions(rtol=1e-7, atol=1e-9)
    shown = runner.invoke(app, ["info", str(path)])
    assert shown.exit_code == 0, shown.output
    assert "tsit5, rtol 1e-07, atol 1e-09" in shown.output


def test_cli_flags_fill_the_solver_table(tmp_path):
    config = train_config_from(None, {"dataset": "d.h5", "method": "dopri5", "rtol": 1e-5})
    assert config.solver == SolverOptions(method="dopri5", rtol=1e-5, atol=1e-4, controller="i",
                                          compile="auto")
    assert "solver" in config.model_fields_set
    # A config file's table (or its old flat fields) lies beneath the options given.
    (tmp_path / "c.toml").write_text('rtol = 1e-3\n[solver]\natol = 1e-6\n')
    config = train_config_from(tmp_path / "c.toml",
                               {"dataset": "d.h5", "fixed_dt": 0.1, "method": "rk4"})
    assert config.solver == SolverOptions(method="rk4", rtol=1e-3, atol=1e-6, fixed_dt=0.1,
                                          controller="i", compile="auto")
    for verb in (["train", "d.h5"], ["generate", "lorenz"]):
        result = runner.invoke(app, [*verb, "--method", "rk4"])
        assert result.exit_code == 2, result.output
        assert "Error: solver: method 'rk4' has no error estimate" in result.output
    result = runner.invoke(app, ["train", "d.h5", "--method", "rk5"])
    assert result.exit_code == 2 and "solver.method: Input should be 'tsit5'" in result.output


def test_training_compiles_long_adaptive_runs_only(monkeypatch):
    from mpnode_cli.training import recipe

    monkeypatch.setattr(recipe, "have_cxx", lambda: True)
    # 2 batches of 32 per epoch: 1500 epochs = 3000 optimizer steps.
    long = TrainConfig(dataset="d.h5", epochs=1500, batch_size=32)
    assert recipe.resolve_compile(long, 64).solver.compile is True
    assert recipe.resolve_compile(long, 64).solver.controller == "i"  # the rest is kept
    assert recipe.resolve_compile(long.model_copy(update={"epochs": 1499}), 64).solver.compile \
        is False
    curriculum = long.model_copy(update={"horizon_curriculum": True})
    assert recipe.resolve_compile(curriculum, 64).solver.compile is True  # dynamic shapes
    fixed = long.model_copy(update={"solver": long.solver.model_copy(update={"fixed_dt": 0.1})})
    assert recipe.resolve_compile(fixed, 64).solver.compile is False  # compile is adaptive-only
    explicit = TrainConfig(dataset="d.h5", epochs=10, solver={"compile": True})
    assert recipe.resolve_compile(explicit, 64).solver.compile is True
    monkeypatch.setattr(recipe, "have_cxx", lambda: False)
    assert recipe.resolve_compile(long, 64).solver.compile is False
    # "auto" that nothing settles means no compile.
    assert SolverOptions(compile="auto").solve_kwargs()["compile"] is False


def test_a_failed_compile_falls_back_to_the_eager_step(monkeypatch):
    import warnings

    import torch

    from mpnode_cli.solver import solve

    def broken(fn, **options):
        def step(*args):
            raise RuntimeError("no C++ compiler\nmore detail")
        return step

    options = SolverOptions(compile=True)  # a fresh cache, whose compiled step fails
    cache = options.solve_kwargs()["compile"]
    assert cache is options.model_copy(update={"rtol": 1e-5}).solve_kwargs()["compile"]
    assert options == SolverOptions(compile=True)  # the cache is no part of the value
    monkeypatch.setattr(torch, "compile", broken)
    y0 = torch.tensor([[1.0]], dtype=torch.float64)
    ts = torch.linspace(0.0, 1.0, 5, dtype=torch.float64)
    with pytest.warns(RuntimeWarning, match="no C\\+\\+ compiler"):
        sol = solve(lambda t, y: -y, y0, ts, **options.solve_kwargs())
    assert torch.allclose(sol.ys[0, :, 0], torch.exp(-ts), rtol=1e-6)
    assert cache.failed
    with warnings.catch_warnings():  # later solves with these options run eagerly, silently
        warnings.simplefilter("error")
        again = solve(lambda t, y: -y, y0, ts, **options.solve_kwargs())
    assert torch.equal(again.ys, sol.ys)


def test_each_controller_option_names_a_typed_controller():
    from typing import get_args

    from mpnode_cli.solver.controller import CONTROLLERS, IController, PIController, controller_for

    assert set(get_args(SolverOptions.model_fields["controller"].annotation)) == set(CONTROLLERS)
    assert controller_for("pi") == PIController(beta1=0.85, beta2=0.25, rtol=1e-6, atol=1e-8)
    assert controller_for("i", 1e-4, 1e-5) == IController(beta1=1.0, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="choose from: pi, i"):
        controller_for("pid")
    # The options build the controller, which carries their tolerances to the error test.
    kwargs = SolverOptions(rtol=1e-4, atol=1e-5, controller="i").solve_kwargs()
    assert kwargs["controller"] == IController(rtol=1e-4, atol=1e-5)
    assert "rtol" not in kwargs and "atol" not in kwargs
