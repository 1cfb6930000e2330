"""MP-NODE's affine node update: linear in the neighbours' summed messages, so what it learns
from one degree holds at any other (a closed form and a finite-difference property)."""

from __future__ import annotations

import pytest
import torch

from mpnode_cli.models.options import MPNODEOptions
from mpnode_cli.models.registry import build_model
from mpnode_cli.solver.options import SolverOptions

pytestmark = pytest.mark.usefixtures("float64_default")


def star(leaves: int, batch: int = 1) -> torch.Tensor:
    """`[B, N, N]`: node 0 hears every leaf; each leaf hears node 0 (N = leaves + 1)."""
    n = leaves + 1
    a = torch.zeros(batch, n, n)
    a[:, 0, 1:] = 1.0
    a[:, 1:, 0] = 1.0
    return a


def affine_model(**options):
    o = {"update": "affine", "aggregate": "sum", "message_dim": 2, "hidden": 8} | options
    return build_model("mpnode", {"node_dim": 1, **o}).double()


@pytest.mark.parametrize("aggregate", ["sum", "mean"])
def test_the_field_is_affine_in_the_neighbour_messages_at_any_degree(aggregate):
    # Node 0 of a star with d identical leaves: the sum of what they send grows as d, so
    # ẋ₀(d) − ẋ₀(0) must be
    # exactly d · (ẋ₀(1) − ẋ₀(0)) for sum, and constant in d ≥ 1 for the mean, however far
    # d goes beyond any degree seen.
    torch.manual_seed(0)
    model = affine_model(aggregate=aggregate)
    with torch.no_grad():  # the gains start at zero; give them values to test
        torch.nn.init.normal_(model.net[-1].weight)
    x_hub, leaf = torch.tensor([0.3]), torch.tensor([-0.2, 0.7, 0.5])  # leaf: [x, m₁, m₂]

    def hub_rate(d: int) -> torch.Tensor:
        z = torch.cat([torch.cat([x_hub, torch.tensor([0.1, -0.4])])[None], leaf.repeat(d, 1)])
        return model.vector_field(star(d))(torch.zeros(1), z[None])[0, 0, :1]

    base, one = hub_rate(0), hub_rate(1)
    for d in (2, 7, 40, 300):
        expected = base + (d if aggregate == "sum" else 1) * (one - base)
        torch.testing.assert_close(hub_rate(d), expected, rtol=1e-12, atol=1e-12)


def set_constant(net, value: torch.Tensor) -> None:
    """Make an MLP output the constant `value` (last layer: zero weights, bias)."""
    with torch.no_grad():
        net[-1].weight.zero_()
        net[-1].bias.copy_(value)


def test_a_hand_set_additive_system_is_exact_on_a_graph_of_any_degree():
    # Every node sends ψ = s and ẋ_i = g · Σ_j ψ_j = g·s·d_i, hence the closed form
    # x_i(t) = x_i(0) + g·s·d_i·t on every node, whatever its in-degree d_i; the message
    # state follows ṁ = c + G_m · mean ψ = c, so m(t) = c·t.
    model = affine_model(message_dim=1)  # net's out: [F_x, F_m, G_x, G_m]
    g, s, c = 0.5, 2.0, -0.3
    set_constant(model.net, torch.tensor([0.0, c, g, 0.0]))
    set_constant(model.emit, torch.tensor([s]))
    adjacency = star(60)
    adjacency[0, 1:4, 4:7] = torch.eye(3)  # leaves 1–3 also hear leaves 4–6
    x0 = torch.randn(1, 61, 1)
    ts = torch.linspace(0.0, 1.5, 7)
    out = model.rollout(x0, ts, adjacency, solver=SolverOptions(rtol=1e-10, atol=1e-10),
                        return_messages=True)
    degree = adjacency.sum(dim=2)[0]  # (N,)
    expected = x0[0, :, 0] + g * s * degree * ts[:, None]  # (T, N)
    torch.testing.assert_close(out.states[0, :, :, 0], expected, rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(out.messages[0, :, :, 0], c * ts[:, None].expand(7, 61))


def test_learned_initial_messages_are_a_function_of_the_first_state():
    torch.manual_seed(1)
    model = affine_model(message_init="learned")
    x0 = torch.randn(2, 5, 1)
    ts = torch.linspace(0.0, 0.5, 3)
    out = model.rollout(x0, ts, star(4, batch=2), return_messages=True)
    torch.testing.assert_close(out.messages[:, 0], model.init_net(x0))
    assert out.messages[:, 0].abs().sum() > 0
    zero = affine_model(message_init="zero")
    assert zero.rollout(x0, ts, star(4, 2), return_messages=True).messages[:, 0].abs().sum() == 0


def test_training_starts_from_uncoupled_nodes():
    # G = 0 at initialization: a node's rate does not depend on its neighbours yet.
    torch.manual_seed(2)
    model = affine_model()
    z = torch.randn(1, 6, 3)
    alone = model.vector_field(torch.zeros(1, 6, 6))(torch.zeros(1), z)
    torch.testing.assert_close(model.vector_field(star(5))(torch.zeros(1), z), alone)


def test_the_update_option_is_declared_and_refused_where_unknown():
    assert MPNODEOptions().update == "mlp"  # the paper's MLP stays the model's own default
    with pytest.raises(ValueError, match="update"):
        build_model("mpnode", {"node_dim": 1, "update": "bilinear"})
