"""The memory a training step keeps, measured before the first step
(`mpnode_cli.training.step_memory`): checked against torch's own profiler, and a run that
cannot fit refused in one line before its folder exists."""

from __future__ import annotations

import torch
from conftest import one_line_error
from torch.profiler import ProfilerActivity, profile
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.models.ensemble import Ensemble
from mpnode_cli.models.registry import build_model
from mpnode_cli.training import step_memory
from mpnode_cli.training.losses import LOSSES

N, D, H, B = 5, 2, 21, 6


def _batch():
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(B, H, N, D, generator=gen)
    chain = torch.zeros(N, N)
    chain[torch.arange(N - 1), torch.arange(1, N)] = 1
    return x, torch.linspace(0, 2, H), (chain + chain.T).expand(B, N, N).contiguous()


def _model(kind: str = "mpnode", seed: int = 0, **options):
    torch.manual_seed(seed)
    return build_model(kind, {"node_dim": D, "control_dim": 0, "num_nodes": N, "hidden": 16,
                              **options})


def _retained(model, x, ts, graph) -> int:
    """Bytes still allocated when a training loss's forward pass ends (its graph alive),
    by torch's profiler: every allocation less every free, per op."""
    members = len(model.members)
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        losses = model.training_losses(x.expand(members, *x.shape), ts, [graph] * members,
                                       None, LOSSES["mse"], range(members))
    assert all(loss.loss is not None for loss in losses)
    return sum(e.self_cpu_memory_usage for e in prof.key_averages())


def test_one_trajectory_times_the_batch_is_what_the_profiler_sees_a_batch_keep():
    x, ts, graph = _batch()
    for model in (_model(), Ensemble([_model(seed=0), _model(seed=1)])):
        one = step_memory.saved_bytes(model, x[:1], ts, graph[:1], None, None)
        retained = _retained(model, x, ts, graph)
        # A floor: the profiler also counts the rollout's outputs and the loss, and each
        # trajectory here takes its own adaptive steps, so B × one is near, not equal.
        assert 0.7 * retained <= B * one <= 1.05 * retained, (B * one, retained)


def test_an_ensemble_keeps_a_members_worth_per_member():
    x, ts, graph = _batch()
    one = step_memory.saved_bytes(_model(), x[:1], ts, graph[:1], None, None)
    two = step_memory.saved_bytes(Ensemble([_model(seed=0), _model(seed=0)]), x[:1], ts,
                                  graph[:1], None, None)
    assert 1.8 * one <= two <= 2.05 * one, (one, two)


def test_measuring_leaves_torchs_random_state_as_it_was():
    x, ts, graph = _batch()
    model = _model("l2s")  # draws its training noise from torch's global generator
    model.fit_statistics(x, float(ts[1] - ts[0]), graph)
    before = torch.random.get_rng_state()
    assert step_memory.saved_bytes(model, x[:1], ts, graph[:1], None, None) > 0
    assert torch.equal(torch.random.get_rng_state(), before)


def test_a_run_that_cannot_fit_is_refused_in_one_line_before_its_folder(
        user_files, tmp_path, monkeypatch):
    monkeypatch.setattr(step_memory, "available_memory", lambda: 1024)
    run = tmp_path / "run"
    result = CliRunner().invoke(app, ["train", str(user_files["data"]), "--epochs", "1",
                                      "--no-plots", "--run-dir", str(run)])
    line = one_line_error(result)
    assert "a training step needs at least" in line and "--batch-size" in line, line
    assert not run.exists()


def test_measuring_never_saves_more_than_it_may_take():
    """The measurement's own graph is capped: under a room below one solver step's bytes
    the need is infinite (a refusal), and under a few steps' room it is still near the
    whole rollout's, measured on one step and extrapolated (the solve's fixed cost spread
    over one step's evaluations: a third more, not less)."""
    from mpnode_cli.config.fields import train_solver

    x, ts, graph = _batch()
    model, x, graph = _model(), x[:1], graph[:1]
    solver = train_solver().model_copy(update={"compile": False, "fixed_dt": 0.01})
    whole = step_memory.saved_bytes(model, x, ts, graph, None, solver)  # 200 steps, no cap
    one_step = step_memory.saved_bytes(model, x, ts, graph, None,
                                       solver.model_copy(update={"max_steps": 1}))
    assert whole > 50 * one_step
    need = step_memory.batch_need(model, x, ts, graph, None, solver, 8, room=one_step // 2)
    assert all(v == float("inf") for v in need), need
    need = step_memory.batch_need(model, x, ts, graph, None, solver, 8, room=4 * one_step)
    assert 0.95 * 8 * whole <= need.plain <= 1.5 * 8 * whole, (need, whole)


def test_a_horizon_the_solver_cannot_finish_is_refused_before_its_folder(tmp_path):
    """Samples 10⁶ time units apart: the model's solve of one trajectory cannot finish in
    --max-steps, so every batch would fail; refused in one line, no run folder."""
    import numpy as np
    from conftest import invoke

    states = tmp_path / "states.npy"
    np.save(states, np.random.default_rng(0).normal(size=(8, 6, 3, 2)).astype("f4"))
    edges = tmp_path / "ring.txt"
    edges.write_text("0 1\n1 2\n2 0\n")
    data, run = tmp_path / "long.h5", tmp_path / "run"
    assert invoke("import", "--states", states, "--edge-list", edges, "--dt", 1e6,
                  "--out", data).exit_code == 0
    line = one_line_error(invoke("train", data, "--epochs", 1, "--no-plots", "--max-steps",
                                 200, "--run-dir", run))
    assert "does not finish its horizon" in line and "--max-steps 200" in line, line
    assert not run.exists()
