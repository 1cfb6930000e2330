"""Ensembles (`train --seeds S`): a member is the model of its seed trained alone, the
members integrate in one solve, and each keeps its own schedule, skips and early stop."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from torch.func import functional_call

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.graphs.matrices import EdgeBatch
from mpnode_cli.models.base import NeuralModel
from mpnode_cli.models.ensemble import Ensemble
from mpnode_cli.models.registry import build_model
from mpnode_cli.models.stacked import LayerNorm, Linear, StackedMembers
from mpnode_cli.training import distributed, epoch_record, step
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.checkpoint_contents import checkpoint_problems
from mpnode_cli.training.eval_result import EvalResult
from mpnode_cli.training.loop import train
from mpnode_cli.training.optim import Adam
from mpnode_cli.training.run import checkpoint_path, read_metrics


@pytest.fixture
def gene(gene_2x2):
    return gene_2x2


def config(dataset, run_dir, **kw) -> TrainConfig:
    """Five epochs in batches of 16 at lr 1e-2, no plots; `kw` on top."""
    return TrainConfig(**({"dataset": dataset, "run_dir": run_dir, "batch_size": 16,
                           "lr": 1e-2, "epochs": 5, "plots": False} | kw))


def members(kind: str, options: dict, s: int = 3, control_dim: int = 1) -> list:
    out = []
    for k in range(s):
        torch.manual_seed(k)
        out.append(build_model(kind, {"node_dim": 2, "control_dim": control_dim,
                                      "num_nodes": 5, **options}).double())
    return out


def test_stacked_layers_are_each_members_own_layer():
    torch.manual_seed(0)
    w, b = torch.randn(3, 4, 5, dtype=torch.float64), torch.randn(3, 4, dtype=torch.float64)
    x = torch.randn(3 * 7, 2, 5, dtype=torch.float64)  # member-major rows
    g, h = torch.randn(3, 5, dtype=torch.float64), torch.randn(3, 5, dtype=torch.float64)
    linear, norm = Linear(5, 4).double(), LayerNorm(5).double()
    y = functional_call(linear, {"weight": w, "bias": b}, (x,))
    z = functional_call(norm, {"weight": g, "bias": h}, (x,))
    # Re-bound to the kept members' weights (members 0 and 2), the layer runs their rows.
    stacked = StackedMembers({"weight": w, "bias": b})
    kept = torch.cat([x[:7], x[14:]])
    y2 = stacked.kept(linear, torch.tensor([0, 2]), linear)(kept)
    assert torch.allclose(y2, torch.cat([y[:7], y[14:]]), atol=1e-12)
    assert linear.weight.shape == (4, 5)  # the layer's own weight is back
    # An ordinary weight is torch's own layer.
    assert torch.equal(linear(x), F.linear(x, linear.weight, linear.bias))
    for k in range(3):
        rows = slice(7 * k, 7 * (k + 1))
        assert torch.allclose(y[rows], x[rows] @ w[k].T + b[k], atol=1e-12)
        mean = x[rows].mean(-1, keepdim=True)
        var = x[rows].var(-1, keepdim=True, correction=0)
        assert torch.allclose(z[rows], (x[rows] - mean) / torch.sqrt(var + 1e-5) * g[k] + h[k],
                              atol=1e-10)


@pytest.mark.parametrize("kind", ["mpnode", "l2s"])
def test_an_ensemble_implements_the_model_interface_itself(kind):
    models = members(kind, {}, s=2)
    ensemble = Ensemble(models)
    assert isinstance(ensemble, NeuralModel)
    assert "__getattr__" not in vars(Ensemble)  # nothing forwarded to a member
    for name in ("kind", "transferable", "statistics_need_states", "options", "node_dim",
                 "control_dim", "num_nodes", "initial_states"):
        assert getattr(ensemble, name) == getattr(models[0], name), name
    assert ensemble.config == models[0].config | {"members": 2}
    for name in ("fit_statistics", "rollout", "training_losses"):
        assert callable(vars(Ensemble).get(name)), name
    with pytest.raises(TypeError, match="training_losses"):  # one model's, not the ensemble's
        ensemble.training_loss(None, None, None, None, None)
    assert ensemble.member_state(ensemble.state_dict(), 1).keys() == (
        models[1].state_dict().keys())
    with pytest.raises(ValueError, match="features per node"):
        ensemble.check_states(torch.zeros(1, 5, 3))


def test_a_single_model_is_an_ensemble_of_one():
    (model,) = members("mpnode", {}, s=1, control_dim=0)
    model.fit_statistics(None, 0.1, torch.ones(1, 5, 5))
    assert model.members == (model,)
    g = torch.Generator().manual_seed(4)
    x = torch.randn(1, 3, 6, 5, 2, generator=g, dtype=torch.float64)  # member axis S = 1
    ts = torch.linspace(0, 1, 6, dtype=torch.float64)
    adjacency = torch.ones(3, 5, 5, dtype=torch.float64)

    def loss(p, t):
        return (p - t).square().mean()

    (batch,) = model.training_losses(x, ts, [adjacency], None, loss, [0])
    alone = model.rollout(x[0, :, 0], ts, adjacency)  # the whole-horizon rollout from x(t₀)
    assert torch.equal(batch.loss, loss(alone.states, x[0]))


@pytest.mark.parametrize("kind, options, edges", [
    ("mpnode", {}, False), ("mpnode", {"backend": "scatter"}, True),
    ("mpnode", {"update": "mlp", "aggregate": "pna"}, False), ("gnode", {"graph": "sys"}, False),
    ("node", {}, False)])
def test_one_solve_equals_each_member_alone(kind, options, edges):
    torch.manual_seed(1)
    b, t = 4, 9
    ts = torch.linspace(0, 1, t, dtype=torch.float64)
    adjacency = (torch.rand(b, 5, 5) < 0.4).double()
    graph = EdgeBatch.from_adjacency(adjacency) if edges else adjacency
    models = members(kind, options)
    for m in models:
        m.fit_statistics(None, 0.1, adjacency)
    x0 = torch.randn(b, 5, 2, dtype=torch.float64)
    u = torch.randn(b, t, 5, 1, dtype=torch.float64)
    out = Ensemble(models).rollout(x0, ts, graph, u)
    alone = torch.stack([m.rollout(x0, ts, graph, u).states for m in models])
    assert torch.allclose(out.members, alone, rtol=0, atol=1e-12)
    assert torch.allclose(out.states, alone.mean(0), atol=1e-12)
    assert torch.allclose(out.spread, alone.std(0, correction=0), atol=1e-12)
    # Gradients reach every member's own tensors, as each member's rollout alone gives them.
    out.members[1].square().sum().backward()
    alone_grads = torch.autograd.grad(models[1].rollout(x0, ts, graph, u).states.square().sum(),
                                      list(models[1].parameters()), allow_unused=True)
    for p, g in zip(models[1].parameters(), alone_grads, strict=True):
        assert p.grad is not None and g is not None
        assert torch.allclose(p.grad, g, rtol=1e-8, atol=1e-10)
    assert all(p.grad is None or not p.grad.any() for p in models[0].parameters())


def test_a_member_trains_as_its_seed_alone(gene, tmp_path):
    # In float64, so that the comparison sees the training, not float32 round-off (a
    # batched matmul rounds otherwise than a member's own), which training amplifies.
    # Three epochs: the members' batch orders, noise and schedules part after the first.
    ensemble = train(config(gene, tmp_path / "ens", seed=5, seeds=3, dtype="float64",
                            epochs=3))
    rows = read_metrics(tmp_path / "ens")
    assert ensemble.members and [m["seed"] for m in ensemble.members] == [5, 6, 7]
    for k, seed in enumerate((5, 6, 7)):
        alone = read_metrics(train(config(gene, tmp_path / f"alone{seed}", seed=seed,
                                          dtype="float64", epochs=3)).run_dir)
        assert len(alone) == len(rows) == 4
        for mine, theirs in zip(rows, alone, strict=True):
            member = mine["members"][k]
            assert member["val_loss"] == pytest.approx(theirs["val_loss"], rel=1e-4)
            if theirs["train_loss"] is not None:
                assert member["train_loss"] == pytest.approx(theirs["train_loss"], rel=1e-4)
        # The member's best epoch is one whose loss ties the alone run's best to the
        # rounding the losses are compared at (stacked and plain weights round apart).
        best = ensemble.members[k]["best_epoch"]
        assert alone[best]["epoch"] == best
        assert alone[best]["val_loss"] == pytest.approx(min(r["val_loss"] for r in alone),
                                                        rel=1e-4)
    assert rows[-1]["val_loss"] == pytest.approx(
        sum(m["val_loss"] for m in rows[-1]["members"]) / 3)
    ckpt = load_checkpoint(checkpoint_path(tmp_path / "ens", "last"))
    assert ckpt.model_config["members"] == 3 and checkpoint_problems(ckpt) == []


def test_an_ensemble_resumes_exactly(gene, tmp_path):
    whole = train(config(gene, tmp_path / "whole", seeds=2, epochs=4))
    train(config(gene, tmp_path / "parts", seeds=2, epochs=2))
    train(config(gene, tmp_path / "parts", seeds=2, epochs=4), resume=True)
    strip = [{k: v for k, v in r.items() if "seconds" not in k}
             for r in read_metrics(whole.run_dir)]
    again = [{k: v for k, v in r.items() if "seconds" not in k}
             for r in read_metrics(tmp_path / "parts")]
    for r in strip + again:
        for m in r.get("members", []):
            m.pop("train_seconds", None)
    assert strip == again
    a = load_checkpoint(checkpoint_path(whole.run_dir, "best")).state_dict
    b = load_checkpoint(checkpoint_path(tmp_path / "parts", "best")).state_dict
    assert all(torch.equal(a[k], b[k]) for k in a)


def _fake_validation(schedule):
    """`evaluate` replaced: member k's validation MSE at each call is `schedule(call, k)`."""
    calls = []

    def fake(model, data, normalizer, **kw):
        n = len(calls)
        calls.append(n)
        size = len(model.members)
        each = [EvalResult(len(data), 0, schedule(n, k), schedule(n, k), [1.0], [0.0], 0, 0.0)
                for k in range(size)]
        return EvalResult(len(data), 0, sum(e.mse for e in each) / size, 0.0, [1.0], [0.0],
                          0, 0.0, members=each if size > 1 else None)
    return fake


def test_early_stopping_freezes_a_member_and_ends_the_run(gene, tmp_path, monkeypatch):
    # Member 0 improves every epoch; member 1 never after its start.
    monkeypatch.setattr(epoch_record, "evaluate", _fake_validation(
        lambda n, k: 1.0 / (n + 1) if k == 0 else 1.0))
    summary = train(config(gene, tmp_path / "run", seeds=2, epochs=6, stop_patience=2))
    rows = read_metrics(tmp_path / "run")
    assert [m["stopped"] for m in summary.members] == [0, 2]
    assert summary.epochs == 6 and summary.stopped_early is None
    assert all(r["members"][1].get("train_loss") is None for r in rows[3:])
    # Member 1 stopped after epoch 2: its weights at the end are those of a run of 2 epochs.
    monkeypatch.setattr(epoch_record, "evaluate", _fake_validation(
        lambda n, k: 1.0 / (n + 1) if k == 0 else 1.0))
    train(config(gene, tmp_path / "two", seeds=2, epochs=2, stop_patience=2))
    two = load_checkpoint(checkpoint_path(tmp_path / "two", "last")).state_dict
    last = load_checkpoint(checkpoint_path(tmp_path / "run", "last")).state_dict
    frozen = [k for k in last if k.startswith("members.1.")]
    assert frozen and all(torch.equal(two[k], last[k]) for k in frozen)
    assert not all(torch.equal(two[k], last[k]) for k in last if k.startswith("members.0."))
    # Nobody improves: the run ends once both have waited stop_patience epochs.
    monkeypatch.setattr(epoch_record, "evaluate", _fake_validation(lambda n, k: 1.0))
    ended = train(config(gene, tmp_path / "ended", seeds=2, epochs=9, stop_patience=3))
    assert ended.epochs == 3 and ended.stopped_early == 3


def test_a_members_bad_batch_leaves_it_alone_and_the_others_step():
    torch.manual_seed(0)
    models = members("mpnode", {}, s=2, control_dim=0)
    for m in models:
        m.fit_statistics(None, 0.1, torch.ones(1, 5, 5))
    ensemble = Ensemble(models)
    alone = members("mpnode", {}, s=1, control_dim=0)[0]
    alone.fit_statistics(None, 0.1, torch.ones(1, 5, 5))
    optimizer = Adam([{"params": list(m.parameters())} for m in models], lr=1e-2)
    optimizer_alone = Adam(alone.parameters(), lr=1e-2)
    ts = torch.linspace(0, 1, 6, dtype=torch.float64)
    x = torch.randn(2, 3, 6, 5, 2, dtype=torch.float64)
    adjacency = (torch.rand(3, 5, 5) < 0.5).double()
    calls = []

    def loss(pred, target):  # member 1's loss is NaN
        calls.append(1)
        return (pred - target).square().mean() * (math.nan if len(calls) == 2 else 1.0)

    before = [p.detach().clone() for p in models[1].parameters()]
    cfg = TrainConfig(dataset="x.h5")
    world = distributed.world()
    out = step.train_step(ensemble, optimizer, [(x[0], None), (x[1], None)], ts,
                     [adjacency, adjacency], loss, cfg, world, [0, 1])
    assert out[0].skip is None and out[1].skip == "non-finite loss"
    assert all(torch.equal(p, q) for p, q in zip(models[1].parameters(), before, strict=True))
    assert not any(p in optimizer.state for p in models[1].parameters())
    (solo,) = step.train_step(alone, optimizer_alone, [(x[0], None)], ts, [adjacency],
                         lambda p, t: (p - t).square().mean(), cfg, world)
    assert solo.loss == pytest.approx(out[0].loss, rel=1e-12)
    for p, q in zip(models[0].parameters(), alone.parameters(), strict=True):
        assert torch.allclose(p, q, atol=1e-12)


def test_a_finetune_takes_its_checkpoints_members(gene, tmp_path):
    """A single model finetunes as one: members copied from it would all start from its
    weights, their spread measuring nothing. An ensemble finetunes member by member."""
    parent = train(config(gene, tmp_path / "parent", epochs=1))
    with pytest.raises(ValueError, match="the checkpoint holds 1 member"):
        train(config(gene, tmp_path / "copies", epochs=1, seeds=3,
                     init_checkpoint=checkpoint_path(parent.run_dir, "best")))
    child = train(config(gene, tmp_path / "child", epochs=2, seeds=3))
    with pytest.raises(ValueError, match="holds 3 member"):
        train(config(gene, tmp_path / "grandchild", epochs=1, seeds=2,
                     init_checkpoint=checkpoint_path(child.run_dir, "best")))
    other = generate(GenerateConfig(system="gene", grid=2, topology="ba", trajectories=12,
                                    t_end=2.0, dt=0.1, out=tmp_path / "other.h5")).path
    with pytest.raises(ValueError, match="trains on one dataset"):
        train(config([gene, other], tmp_path / "pooled", epochs=1,
                     init_checkpoint=checkpoint_path(child.run_dir, "best")))
    assert not any((tmp_path / name).exists() for name in ("copies", "grandchild", "pooled"))



def test_an_ensembles_config_keeps_what_its_kind_adds():
    """MP-NODE adds `periodic_dims` to its config where it embeds angles: an ensemble's
    config must carry it too, or its checkpoint would not build again."""
    one = {"node_dim": 2, "control_dim": 0, "periodic": "embed", "periodic_dims": [0],
           "hidden": 8}
    model = build_model("mpnode", {**one, "members": 3})
    assert model.config["periodic_dims"] == [0] and model.config["members"] == 3
    again = build_model("mpnode", model.config)
    assert again.config == model.config
    assert [m.periodic_dims for m in again.members] == [(0,)] * 3
