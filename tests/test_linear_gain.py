"""MP-NODE's `gain="linear"`: the affine update's gains as an affine map of the node's own
inputs, G(x, u) = W·[x, u] + b, zero at first.

Checked against properties that hold whatever the weights: the field is affine in the
node's own state along any line once the drift and the messages are held (second
differences vanish), zero gains leave the nodes uncoupled (the field equals the same
nodes' on an empty graph), an ensemble stacks the gain like its other weights, the
option is refused where there is no gain, and checkpoints from before it load.
"""

from __future__ import annotations

import pytest
import torch

from mpnode_cli.models.ensemble import Ensemble
from mpnode_cli.models.registry import build_model

F64 = torch.float64
AFFINE = {"update": "affine", "aggregate": "sum", "message_init": "learned"}


def model(seed: int = 0, **options):
    torch.manual_seed(seed)
    m = build_model("mpnode", {"node_dim": 2, "control_dim": 1, **AFFINE, **options}).double()
    m.fit_statistics(None, 0.1, torch.ones(1, 5, 5))
    return m


def randomize(m, name: str, seed: int, scale: float = 0.5):
    """Give the parameters whose names start with `name` random values (they start at 0)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for key, p in m.named_parameters():
            if key.startswith(name):
                p.copy_(scale * torch.randn(p.shape, generator=g, dtype=F64))


def graph_and_inputs(seed: int = 1, b: int = 2, n: int = 5):
    g = torch.Generator().manual_seed(seed)
    adjacency = (torch.rand(b, n, n, generator=g) < 0.6).to(F64)
    adjacency *= 1 - torch.eye(n, dtype=F64)
    z = torch.randn(b, n, 2 + 3, generator=g, dtype=F64)  # [x (2); m (3)]
    u = torch.randn(b, n, 1, generator=g, dtype=F64)
    return adjacency, z, u


def test_the_gain_is_a_linear_map_and_the_mlp_no_longer_outputs_it():
    plain, linear = model(), model(gain="linear")
    assert plain.options.gain == "mlp" and linear.options.gain == "linear"
    d, m, c = 2, 3, 3  # sum aggregation: one channel per message
    gains = d * c + m * m
    assert plain.net[-1].out_features == d + m + gains
    assert linear.net[-1].out_features == d + m
    assert tuple(linear.gain.weight.shape) == (gains, 2 + 1)  # [x, u] → the gains
    assert not linear.gain.weight.any() and not linear.gain.bias.any()


def test_zero_gains_leave_the_nodes_uncoupled():
    # Untrained, every gain is 0: each node's field is what it is on an empty graph,
    # however large its in-degree.
    net = model(gain="linear")
    randomize(net, "net.", 2)
    randomize(net, "emit.", 3)
    adjacency, z, u = graph_and_inputs()
    t = torch.zeros(2, dtype=F64)
    coupled = net.vector_field(adjacency, lambda _: u)(t, z)
    alone = net.vector_field(torch.zeros_like(adjacency), lambda _: u)(t, z)
    assert torch.equal(coupled, alone)
    assert adjacency.sum(dim=2).max() >= 3  # the check would catch a coupled field


def test_the_coupling_term_is_affine_in_the_receivers_own_state():
    # dz_i/dt − (the same node on an empty graph) = G(x_i, u_i)·Σ_j ψ_j: with the senders
    # held, it is affine in the receiver's x_i along any line, here far outside any range
    # a tanh MLP would follow (|x| up to 40 in normalized units). An MLP gain is not.
    adjacency, z, u = graph_and_inputs()
    t = torch.zeros(2, dtype=F64)
    receiver, direction = 0, torch.tensor([1.0, -0.7], dtype=F64)

    def coupling(net, s: float) -> torch.Tensor:
        zs = z.clone()
        zs[:, receiver, :2] += s * direction
        field = net.vector_field(adjacency, lambda _: u)(t, zs)
        alone = net.vector_field(torch.zeros_like(adjacency), lambda _: u)(t, zs)
        return (field - alone)[:, receiver]

    def second_difference(net, s: float, h: float) -> torch.Tensor:
        return coupling(net, s + h) - 2 * coupling(net, s) + coupling(net, s - h)

    linear, plain = model(gain="linear"), model()
    for net, seed in ((linear, 4), (plain, 4)):
        randomize(net, "", seed)
    scale = coupling(linear, 40.0).abs().max()
    assert scale > 1e-2  # the coupling is not zero
    for s in (0.0, 5.0, 40.0):
        assert second_difference(linear, s, 3.0).abs().max() <= 1e-12 * scale * 40
    # The receiver's messages are held too (they enter the gain of neither model), so only
    # the MLP gain's curvature in x_i can show here.
    assert second_difference(plain, 0.0, 1.0).abs().max() > 1e-4


def test_an_ensemble_stacks_the_gain_as_its_members_alone():
    def members():
        out = []
        for k in range(2):
            m = model(seed=k, gain="linear")
            randomize(m, "gain.", 20 + k, scale=0.3)
            out.append(m)
        return out

    g = torch.Generator().manual_seed(5)
    x0 = torch.randn(3, 5, 2, generator=g, dtype=F64)
    ts = torch.linspace(0, 1, 6, dtype=F64)
    adjacency = (torch.rand(3, 5, 5, generator=g) < 0.5).to(F64)
    u = torch.randn(3, 6, 5, 1, generator=g, dtype=F64)
    together = Ensemble(members()).rollout(x0, ts, adjacency, u)
    each = torch.stack([m.rollout(x0, ts, adjacency, u).states for m in members()])
    assert torch.allclose(together.members, each, rtol=0, atol=1e-12)


def test_without_the_affine_update_it_is_refused():
    with pytest.raises(ValueError, match="gain linear shapes the affine update's gain"):
        build_model("mpnode", {"node_dim": 2, "update": "mlp", "gain": "linear"})


def test_a_checkpointed_config_from_before_the_option_builds_the_mlp_gain():
    # A model config saved before the option has no `gain`: it builds today's model, whose
    # weights are the same names and shapes.
    today = model()
    config = dict(today.config)
    config.pop("gain")
    old = build_model("mpnode", {**config, "node_dim": 2, "control_dim": 1})
    assert old.options.gain == "mlp"
    assert {k: v.shape for k, v in old.state_dict().items()} == {
        k: v.shape for k, v in today.state_dict().items()}
