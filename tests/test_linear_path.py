"""MP-NODE's `linear_path` option: a linear map beside each node network's MLP,
F(z) = A·z + MLP(z), with A zero at first.

Off by default and zero when on, so an untrained model is today's; far outside the training
range the field grows linearly where a tanh MLP saturates; an ensemble stacks the path like
its other weights; and checkpoints with it, without it, and from before it load.
"""

from __future__ import annotations

import pytest
import torch

from mpnode_cli.config import TrainConfig
from mpnode_cli.models.ensemble import Ensemble
from mpnode_cli.models.registry import build_model
from mpnode_cli.training import loop
from mpnode_cli.training.checkpoint import (
    checkpoint_problems,
    load_checkpoint,
    save_checkpoint,
)
from mpnode_cli.training.checkpoint_members import member_checkpoint
from mpnode_cli.training.loop import train
from mpnode_cli.training.optim import Adam
from mpnode_cli.training.run import checkpoint_path

F64 = torch.float64
AFFINE = {"update": "affine", "aggregate": "sum", "message_init": "learned"}
# Today's weight names (before the option) of a model with every node network.
TODAYS_AFFINE_KEYS = [
    f"{net}.{i}.{w}" for net, layers in (("net", (0, 2, 4)), ("emit", (0, 2)),
                                        ("init_net", (0, 2)))
    for i in layers for w in ("weight", "bias")]
PATHS = ["net.linear_weight", "emit.linear_weight", "init_net.linear_weight"]


def model(seed: int = 0, **options):
    torch.manual_seed(seed)
    return build_model("mpnode", {"node_dim": 2, "control_dim": 1, **options}).double()


def rollout_inputs(seed: int = 1, b: int = 3, t: int = 7, n: int = 5):
    g = torch.Generator().manual_seed(seed)
    adjacency = (torch.rand(b, n, n, generator=g) < 0.5).to(F64)
    x0 = torch.randn(b, n, 2, generator=g, dtype=F64)
    u = torch.randn(b, t, n, 1, generator=g, dtype=F64)
    return x0, torch.linspace(0, 1, t, dtype=F64), adjacency, u


@pytest.mark.parametrize("options", [{}, AFFINE])
def test_off_by_default_and_zero_when_on(options):
    off, on = model(**options), model(**options, linear_path=True)
    assert off.options.linear_path is False
    paths = [k for k in PATHS if k in on.state_dict()]
    assert paths == (PATHS if options else PATHS[:1])
    if options:
        assert list(off.state_dict()) == TODAYS_AFFINE_KEYS
    # On: today's weights, drawn alike, plus the paths, all zero.
    assert sorted(on.state_dict()) == sorted(list(off.state_dict()) + paths)
    for name, value in off.state_dict().items():
        assert torch.equal(on.state_dict()[name], value), name
    assert all(not on.state_dict()[k].any() for k in paths)
    x0, ts, adjacency, u = rollout_inputs()
    a = off.rollout(x0, ts, adjacency, u, return_messages=True)
    b = on.rollout(x0, ts, adjacency, u, return_messages=True)
    assert torch.equal(a.states, b.states) and torch.equal(a.messages, b.messages)


# A linear node: dx_i/dt = a·x_i + c·Σ_j A_ij x_j. The model's node network is MP-NODE's
# MLP update over the sum of one message state per node; its inputs are the states x and
# messages that carry them (m = x), so the node network's target is linear in its inputs
# [x_i, Σ_j m_j]. The vector field is fitted by regression on states in [-1, 1] (no ODE).
A_SELF, C_NEIGHBOURS, NODES = -0.7, 0.4, 6


def linear_node(x: torch.Tensor, adjacency: torch.Tensor) -> torch.Tensor:
    return A_SELF * x + C_NEIGHBOURS * (adjacency @ x)


def node_graphs(k: int, g: torch.Generator) -> torch.Tensor:
    adjacency = (torch.rand(k, NODES, NODES, generator=g, dtype=F64) < 0.4).to(F64)
    adjacency.diagonal(dim1=1, dim2=2).zero_()
    return adjacency


def field(net, x: torch.Tensor, adjacency: torch.Tensor) -> torch.Tensor:
    """The model's dx/dt `[K, N, 1]` at states x `[K, N, 1]`, messages m = x."""
    f = net.vector_field(adjacency)
    return f(torch.zeros(x.shape[0], dtype=F64), torch.cat([x, x], dim=-1))[..., :1]


def linear_node_model(linear_path: bool):
    torch.manual_seed(0)
    return build_model("mpnode", {"node_dim": 1, "message_dim": 1, "update": "mlp",
                                  "aggregate": "sum", "linear_path": linear_path}).double()


def fit(net, params, x, adjacency, iters: int) -> float:
    """Least squares of the field against the linear node (L-BFGS); its max residual."""
    target = linear_node(x, adjacency)
    optimizer = torch.optim.LBFGS(params, max_iter=iters, tolerance_grad=1e-14,
                                  tolerance_change=1e-16, history_size=50,
                                  line_search_fn="strong_wolfe")

    def closure():
        optimizer.zero_grad()
        loss = (field(net, x, adjacency) - target).square().mean()
        loss.backward()
        return loss

    optimizer.step(closure)
    with torch.no_grad():
        return float((field(net, x, adjacency) - target).abs().max())


def training_and_far_states():
    g = torch.Generator().manual_seed(1)
    adjacency = node_graphs(32, g)
    x = torch.rand(32, NODES, 1, generator=g, dtype=F64) * 2 - 1  # the training range
    far_graphs = node_graphs(8, g)
    # States of ±25 to ±50: every node's input, and its neighbour sum, far outside.
    far = [sign * 50 * (0.5 + 0.5 * torch.rand(8, NODES, 1, generator=g, dtype=F64))
           for sign in (1, -1)]
    return x, adjacency, far, far_graphs


def far_error(net, far, far_graphs) -> tuple[float, float]:
    """The field's worst error at the far states, and that relative to the field's size."""
    with torch.no_grad():
        errors = [(field(net, x, far_graphs) - linear_node(x, far_graphs)).abs().max()
                  for x in far]
        scale = max(float(linear_node(x, far_graphs).abs().max()) for x in far)
    return float(max(errors)), float(max(errors)) / scale


def test_a_linear_path_holds_a_linear_node_far_outside_the_training_range():
    # The path set directly: the MLP's output weights at zero, the path and the output
    # bias fitted on [-1, 1]. The node network is then affine in its inputs
    # w = [x_i, Σ_j m_j, 1], so its error is Δθ·w with ‖Δθ‖ ≤ ‖residual‖ / σ_min(W) over
    # the training inputs W: the bound at the far states follows from the fit residual.
    x, adjacency, far, far_graphs = training_and_far_states()
    net = linear_node_model(linear_path=True)
    with torch.no_grad():
        net.net[-1].weight.zero_()
    fit(net, [net.net.linear_weight, net.net[-1].bias], x, adjacency, iters=100)
    with torch.no_grad():
        residual = field(net, x, adjacency) - linear_node(x, adjacency)
        inputs = torch.cat([x, adjacency @ x, torch.ones_like(x)], dim=-1).reshape(-1, 3)
        slack = residual.norm() / torch.linalg.svdvals(inputs).min()
        tolerances = []
        for xf in far:
            w = torch.cat([xf, far_graphs @ xf, torch.ones_like(xf)], dim=-1)
            tolerances.append(float(slack * w.norm(dim=-1).max()))
    tolerance = max(tolerances) + 1e-9
    error, _ = far_error(net, far, far_graphs)
    assert float(residual.abs().max()) < 1e-6 and tolerance < 1e-3  # the field: ~60
    assert error <= tolerance

    # The MLP alone, fitted as well on [-1, 1] (every weight), fails that check: a tanh
    # MLP's output is bounded by its output layer, |F| ≤ Σ|W_out| + |b_out|, wherever its
    # input goes, while the linear node's field grows with the states.
    plain = linear_node_model(linear_path=False)
    assert fit(plain, list(plain.parameters()), x, adjacency, iters=100) < 0.05
    error, relative = far_error(plain, far, far_graphs)
    assert error > 1e3 * tolerance and relative > 0.5
    out = plain.net[-1]
    with torch.no_grad():
        bound = float(out.weight[0].abs().sum() + out.bias[0].abs())
        assert all(float(field(plain, xf, far_graphs).abs().max()) <= bound for xf in far)


def test_trained_whole_the_path_extrapolates_better_than_the_mlp_alone():
    # Both node networks fitted from their untrained state, every weight, on [-1, 1]: the
    # MLP beside the path keeps part of the slope (and saturates beyond), so the path does
    # not make the field exact far out; it narrows the error there.
    x, adjacency, far, far_graphs = training_and_far_states()
    errors = {}
    for linear_path in (True, False):
        net = linear_node_model(linear_path)
        assert fit(net, list(net.parameters()), x, adjacency, iters=100) < 0.05
        errors[linear_path] = far_error(net, far, far_graphs)[1]
    assert errors[True] < 0.5 * errors[False]


@pytest.mark.parametrize("options", [AFFINE, {"update": "mlp", "aggregate": "pna"}])
def test_an_ensemble_with_the_path_steps_as_its_members_alone(options):
    # `train --seeds 2`: the members' paths are stacked with their other weights. The paths
    # start nonzero here (each member's own), so the stacked path shows in the rollout.
    def members():
        out = []
        for k in range(2):
            m = model(seed=k, **options, linear_path=True)
            g = torch.Generator().manual_seed(10 + k)
            with torch.no_grad():
                for name, p in m.named_parameters():
                    if name.endswith("linear_weight"):
                        p.copy_(0.3 * torch.randn(p.shape, generator=g, dtype=F64))
            m.fit_statistics(None, 0.1, torch.ones(1, 5, 5))
            out.append(m)
        return out

    models, alone = members(), members()
    x0, ts, adjacency, u = rollout_inputs(b=3, t=6)
    together = Ensemble(models).rollout(x0, ts, adjacency, u)
    each = torch.stack([m.rollout(x0, ts, adjacency, u).states for m in alone])
    assert torch.allclose(together.members, each, rtol=0, atol=1e-12)

    g = torch.Generator().manual_seed(3)
    x = torch.randn(2, 3, 6, 5, 2, generator=g, dtype=F64)  # each member's own batch
    us = torch.randn(2, 3, 6, 5, 1, generator=g, dtype=F64)
    cfg, world = TrainConfig(dataset="x.h5"), loop.distributed.world()

    def loss(p, t):
        return (p - t).square().mean()

    before = {k: p.detach().clone() for k, p in models[1].named_parameters()}
    optimizer = Adam([{"params": list(m.parameters())} for m in models], lr=1e-2)
    for _ in range(2):  # the second step sees the moments of the first
        out = loop.train_step(Ensemble(models), optimizer, [(x[0], us[0]), (x[1], us[1])], ts,
                         [adjacency] * 2, loss, cfg, world, [0, 1])
        assert all(r.skip is None for r in out)
    for k, solo in enumerate(alone):
        optimizer_alone = Adam(solo.parameters(), lr=1e-2)
        for step in range(2):
            (result,) = loop.train_step(solo, optimizer_alone, [(x[k], us[k])], ts, [adjacency],
                                   loss, cfg, world)
            if step == 1:
                assert result.loss == pytest.approx(out[k].loss, rel=1e-12)
        for (name, p), q in zip(models[k].named_parameters(), solo.parameters(), strict=True):
            assert torch.allclose(p, q, rtol=0, atol=1e-12), name
    moved = [k for k, p in models[1].named_parameters() if k.endswith("linear_weight")
             and not torch.equal(p, before[k])]
    assert moved == [k for k in before if k.endswith("linear_weight")] and moved


def test_checkpoints_with_without_and_from_before_the_option(gene_2x2, tmp_path):
    def run(name, **kw):
        cfg = TrainConfig(dataset=gene_2x2, run_dir=tmp_path / name, batch_size=16, lr=1e-2,
                          epochs=1, plots=False, dtype="float64", **kw)
        train(cfg)
        return load_checkpoint(checkpoint_path(tmp_path / name, "last"))

    with_path = run("on", seeds=2, model_options={"linear_path": True})
    without = run("off")
    assert with_path.model_config["linear_path"] is True
    assert without.model_config["linear_path"] is False
    assert not any("linear" in k for k in without.state_dict)
    x = torch.randn(2, 4, 1, dtype=F64)  # gene on a 2×2 grid: 4 nodes, one state
    ts = torch.linspace(0, 1, 5, dtype=F64)
    adjacency = torch.ones(2, 4, 4, dtype=F64)
    for ckpt in (with_path, member_checkpoint(with_path, 1), without):
        built = ckpt.build_model()
        assert {k: v.shape for k, v in built.state_dict().items()} == {
            k: v.shape for k, v in ckpt.state_dict.items()}
        again = save_checkpoint(tmp_path / "again.pt", ckpt)
        rebuilt = load_checkpoint(again).build_model()
        for name, value in built.state_dict().items():
            assert torch.equal(rebuilt.state_dict()[name], value), name
        assert torch.equal(rebuilt.rollout(x, ts, adjacency).states,
                           built.rollout(x, ts, adjacency).states)
    paths = [k for k in with_path.state_dict if k.endswith("linear_weight")]
    assert len(paths) == 2 * 3 and all(with_path.state_dict[k].any() for k in paths)

    # From before the option: no `linear_path` in its model config (nor its train
    # config's model options); it loads as a model without the path.
    without.model_config.pop("linear_path")
    without.train_config["model_options"].pop("linear_path", None)
    old = load_checkpoint(save_checkpoint(tmp_path / "old.pt", without))
    assert "linear_path" not in old.model_config and checkpoint_problems(old) == []
    model_old = old.build_model()
    assert model_old.options.linear_path is False
    assert list(model_old.state_dict()) == list(old.state_dict)
