"""Training within a memory budget (`--memory-budget`, `mpnode_cli.training.step_memory` and
`memory_guard`): checkpointed backprop gives plain backprop's gradients on an MP-NODE
training step (one model and an ensemble); a run whose plain step passes the budget trains
checkpointed, says so and records it, with the plain run's losses; a run whose step
outgrows the budget switches to it after a saved epoch; one that cannot fit is refused in
one line; and the stiffness account warns once when evaluations grow tenfold."""

from __future__ import annotations

import json
import math

import pytest
import torch
from conftest import invoke, one_line_error

from mpnode_cli.config.fields import train_solver
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.memory import parse_size
from mpnode_cli.models.ensemble import Ensemble
from mpnode_cli.models.registry import build_model
from mpnode_cli.solver.checkpoint import Checkpointed
from mpnode_cli.training import memory_guard, step_memory
from mpnode_cli.training.losses import LOSSES
from mpnode_cli.training.run import read_metrics
from mpnode_cli.training.stiffness import GROWTH, Stiffness

N, D, H, B = 5, 2, 21, 4
GIB = 2**30
F64 = torch.float64


def _model(seed: int):
    torch.manual_seed(seed)
    return build_model("mpnode", {"node_dim": D, "control_dim": 0, "num_nodes": N,
                                  "hidden": 16}).to(F64)


def _batch(seed: int):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(B, H, N, D, generator=gen, dtype=F64).cumsum(1) * 0.3  # (B, H, N, D)
    chain = torch.zeros(N, N, dtype=F64)
    chain[torch.arange(N - 1), torch.arange(1, N)] = 1
    return x, torch.linspace(0, 4, H, dtype=F64), (chain + chain.T).expand(B, N, N)


def _gradients(model, checkpoints: int | None) -> list[torch.Tensor]:
    """The parameter gradients of one training step's loss (every member's, summed)."""
    members = len(model.members)
    batches = [_batch(k) for k in range(members)]
    xs = torch.stack([x for x, _, _ in batches])  # (S, B, H, N, D)
    solver = train_solver().model_copy(update={"compile": False, "checkpoints": checkpoints,
                                               "rtol": 1e-8, "atol": 1e-8})
    model.zero_grad(set_to_none=True)
    losses = model.training_losses(xs, batches[0][1], [g for _, _, g in batches], None,
                                   LOSSES["mse"], range(members), solver=solver)
    sum(loss.loss for loss in losses).backward()
    return [p.grad.clone() for p in model.parameters()]


@pytest.mark.parametrize("members", [1, 2])
def test_checkpointed_gradients_are_plain_backprops(members, monkeypatch):
    model = _model(0) if members == 1 else Ensemble([_model(0), _model(1)])
    plain = _gradients(model, None)
    reruns = []
    backward = Checkpointed.backward
    monkeypatch.setattr(Checkpointed, "backward",
                        lambda self, j, grads: reruns.append(j) or backward(self, j, grads))
    checkpointed = _gradients(model, 4)
    assert len(reruns) >= 10  # the steps went through checkpointed nodes
    for a, b in zip(plain, checkpointed, strict=True):
        assert (a - b).norm() <= 1e-10 * a.norm(), ((a - b).norm(), a.norm())


def test_the_plain_need_is_the_whole_rollouts_and_checkpoints_keep_less():
    """Measured on three samples, extrapolated by the evaluations of f: what a whole
    rollout saves; over 400 fixed steps a checkpointed step needs a fraction of it."""
    model, (x, ts, graph) = _model(0).float(), _batch(0)
    x, graph = x[:1].float(), graph[:1].float()
    for solver in (train_solver().model_copy(update={"compile": False}),
                   train_solver().model_copy(update={"compile": False, "fixed_dt": 0.01})):
        whole = step_memory.saved_bytes(model, x, ts, graph, None, solver)
        need = step_memory.batch_need(model, x, ts, graph, None, solver, 8)
        assert 0.9 * 8 * whole <= need.plain <= 1.1 * 8 * whole, (need, whole)
    assert need.step + 64 * need.state < need.plain / 5, need


def _train(data, run, *extra):
    return invoke("train", data, "--epochs", 2, "--batch-size", 16, "--dtype", "float64",
                  "--lr", "1e-2", "--fixed-dt", "0.01", "--no-plots", "--run-dir", run, *extra)


def test_a_budget_that_plain_backprop_passes_trains_checkpointed(gene_2x2, tmp_path,
                                                                   monkeypatch):
    """The budget leaves room between the checkpointed step's need and the plain one's
    (the process's resident memory is set so): the run says so, config.json records 64
    states, and its losses are the plain run's; a resume goes on checkpointed."""
    assert _train(gene_2x2, tmp_path / "plain").exit_code == 0
    needs = []

    def measured(*args):
        needs.append(need := real(*args))
        assert need.step + 64 * need.state < need.plain / 2, need
        return need

    real = step_memory.step_need
    monkeypatch.setattr(step_memory, "step_need", measured)
    monkeypatch.setattr(step_memory, "available_memory", lambda: 2**50)
    monkeypatch.setattr(step_memory, "resident_bytes", lambda: 64 * GIB - int(math.sqrt(
        needs[0].plain * (needs[0].step + 64 * needs[0].state))))
    run = tmp_path / "budget"
    result = _train(gene_2x2, run, "--memory-budget", "64GiB")
    assert result.exit_code == 0, result.output
    assert "backpropagates through checkpointed solves (64 stored states" in result.output
    assert "per sample)" in result.output
    config = json.loads((run / "config.json").read_text())
    assert config["solver"]["checkpoints"] == 64 and config["memory_budget"] == "64GiB"
    rows, plain = read_metrics(run), read_metrics(tmp_path / "plain")
    assert [r["backprop_checkpoints"] for r in rows] == [64] * 3
    assert [r["backprop_checkpoints"] for r in plain] == [None] * 3
    assert all(r["rhs_evals_per_sample"] > 0 for r in rows[1:])
    for a, b in zip(rows[1:], plain[1:], strict=True):
        assert a["train_loss"] == pytest.approx(b["train_loss"], rel=1e-6, abs=0)
        assert a["val_loss"] == pytest.approx(b["val_loss"], rel=1e-6, abs=0)
    monkeypatch.undo()
    result = invoke("train", "--resume", run, "--epochs", 3, "--no-plots")
    assert result.exit_code == 0, result.output
    assert read_metrics(run)[-1]["backprop_checkpoints"] == 64


def test_a_budget_too_small_even_for_checkpoints_is_refused_in_one_line(gene_2x2, tmp_path,
                                                                       monkeypatch):
    monkeypatch.setattr(step_memory, "resident_bytes", lambda: 0)
    run = tmp_path / "run"
    line = one_line_error(_train(gene_2x2, run, "--memory-budget", "2kB"))
    assert "a training step needs at least" in line and "checkpointed" in line, line
    assert "--memory-budget 2kB leaves" in line and "--batch-size" in line, line
    assert not run.exists()
    line = one_line_error(_train(gene_2x2, run, "--memory-budget", "lots"))
    assert "'lots' is not a memory size: give e.g. 4GiB" in line, line


def test_a_step_that_outgrows_the_budget_switches_to_checkpoints(gene_2x2, tmp_path,
                                                                monkeypatch):
    """Peaks of 1, 2 GiB against a 3 GiB budget: two more epochs would pass it, so after
    epoch 2 the run switches (one line, config.json, the next rows); checkpointed, the
    peak falls, and the run finishes."""
    peaks = iter([GIB, 2 * GIB, GIB // 2, GIB // 2])
    init = memory_guard.EpochPeaks.__init__

    def always_on(self, *args):
        init(self, *args)
        self.on = True

    monkeypatch.setattr(memory_guard.EpochPeaks, "__init__", always_on)
    monkeypatch.setattr(memory_guard, "reset_peak", lambda: True)
    monkeypatch.setattr(memory_guard, "peak_bytes", lambda: next(peaks))
    monkeypatch.setattr(memory_guard, "resident_bytes", lambda: GIB // 4)
    monkeypatch.setattr(memory_guard, "available_memory", lambda: 100 * GIB)
    run = tmp_path / "run"
    result = invoke("train", gene_2x2, "--epochs", 4, "--batch-size", 17, "--no-plots",
                    "--memory-budget", "3GiB", "--run-dir", run)
    assert result.exit_code == 0, result.output
    assert "after epoch 2, the training step's peak memory grew" in result.output
    assert "more than the 3 GiB --memory-budget allows" in result.output
    assert [r["backprop_checkpoints"] for r in read_metrics(run)] == [None, None, None, 64, 64]
    assert json.loads((run / "config.json").read_text())["solver"]["checkpoints"] == 64


def test_evaluations_grown_tenfold_warn_once():
    said = []
    watch = Stiffness(said.append)
    for epoch, per in enumerate([5.0, 20.0, 5.0 * GROWTH - 1, 5.0 * GROWTH, 100.0], 1):
        watch.emit({"event": "epoch", "epoch": epoch, "rhs_evals_per_sample": per})
    warnings = [e["text"] for e in said if e["event"] == "warning"]
    assert len(said) == 6 and said[4]["event"] == "warning", said  # after epoch 4's row
    assert len(warnings) == 1 and "grew 10× since epoch 1 (5 → 50)" in warnings[0]
    assert "--max-steps" in warnings[0] and "--clip" in warnings[0]


def test_sizes_and_older_configs():
    assert [parse_size(s) for s in ("4GiB", "1.5GiB", "500MiB", "4G", "4GB", "1000")] == [
        4 * GIB, 3 * GIB // 2, 500 * 2**20, 4 * GIB, 4 * 10**9, 1000]
    for bad in ("0GiB", "-1", "4 apples", "4Gi"):
        with pytest.raises(ValueError, match="is not a memory size"):
            parse_size(bad)
    # A stored config from before `checkpoints` backpropagated through every step.
    stored = TrainConfig(dataset="d.h5").model_dump(mode="json")
    del stored["solver"]["checkpoints"], stored["memory_budget"]
    config = TrainConfig(**stored)
    assert config.solver.checkpoints is None and config.memory_budget is None
