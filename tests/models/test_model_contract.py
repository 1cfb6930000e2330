"""The model contract: an abstract `NeuralModel`, one rollout for the neural ODEs, and
MP-NODE's vector field against its equations written out by hand in numpy."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from torch import nn

from mpnode_cli.models.base import NeuralModel
from mpnode_cli.models.gnode import GNODE
from mpnode_cli.models.l2s import L2S
from mpnode_cli.models.mpnode import MPNODE
from mpnode_cli.models.node import NODE
from mpnode_cli.models.ode import NeuralODEModel
from mpnode_cli.models.options import ModelOptions
from mpnode_cli.models.registry import build_model
from mpnode_cli.models.stacked import Linear
from mpnode_cli.solver.options import SolverOptions

pytestmark = pytest.mark.usefixtures("float64_default")

ODE_KINDS = ("mpnode", "gnode", "node")
D, U, M = 2, 1, 3


def directed_graphs() -> torch.Tensor:
    """`[2, 4, 4]`, `A[b, i, j]` the edges j → i. Graph 0: 1→0, 2→0, 0→1, 1→2 and 3→2
    (two parallel edges: a multigraph, where 3 counts as two of 2's senders); node 3 hears
    no one. Graph 1: 0→1, 0→2, 0→3 and 3→1; node 0 hears no one."""
    a = torch.zeros(2, 4, 4)
    a[0, 0, 1] = a[0, 0, 2] = a[0, 1, 0] = a[0, 2, 1] = 1.0
    a[0, 2, 3] = 2.0
    a[1, 1, 0] = a[1, 2, 0] = a[1, 3, 0] = a[1, 1, 3] = 1.0
    return a


def random_weights(net: nn.Module, seed: int) -> None:
    """Every parameter drawn from N(0, 0.5²): biases nonzero, the affine gains G not zero."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in net.parameters():
            p.copy_(0.5 * torch.randn(p.shape, generator=gen))


def mlp_np(net: nn.Sequential, v: np.ndarray) -> np.ndarray:
    """A tanh MLP (Linear, Tanh, ..., Linear) applied to one input `v: [F]` by numpy."""
    linears = [m for m in net if isinstance(m, nn.Linear)]
    # mpnode's Linear is torch's for an ordinary weight (tests/models/test_ensemble.py checks it).
    kinds = [nn.Linear if type(m) in (nn.Linear, Linear) else type(m) for m in net]
    assert kinds == [nn.Linear, nn.Tanh] * (len(linears) - 1) + [nn.Linear]
    for k, layer in enumerate(linears):
        v = layer.weight.detach().numpy() @ v + layer.bias.detach().numpy()
        if k < len(linears) - 1:
            v = np.tanh(v)
    return v


def in_neighbours(a: np.ndarray, i: int) -> np.ndarray:
    """Node i's senders, each as often as it has edges to i."""
    senders = np.nonzero(a[i])[0]
    return np.repeat(senders, a[i, senders].astype(int))


def field_at_random_point(net: MPNODE, seed: int) -> tuple[np.ndarray, ...]:
    """The model's vector field `[2, 4, D+M]` at a random state `z` with random held
    controls `u` on `directed_graphs()`, and those inputs: (ż, z, u, A) as numpy."""
    gen = torch.Generator().manual_seed(seed)
    z, u = torch.randn(2, 4, D + M, generator=gen), torch.randn(2, 4, U, generator=gen)
    adjacency = directed_graphs()
    dz = net.vector_field(adjacency, lambda t: u)(torch.zeros(2), z)
    return dz.detach().numpy(), z.numpy(), u.numpy(), adjacency.numpy()


def mpnode(**options) -> MPNODE:
    o = {"message_dim": M, "hidden": 5, "layers": 2, "activation": "tanh"} | options
    net = build_model("mpnode", {"node_dim": D, "control_dim": U, **o})
    random_weights(net, seed=1)
    return net


def test_mpnode_mlp_update_is_the_papers_equations():
    # Eqs. (3)–(5): m̄_i = mean of the in-neighbours' current messages m_j (zero for a node
    # that hears no one), and [ẋ_i, ṁ_i] = MLP([x_i, u_i, m̄_i]).
    net = mpnode(update="mlp", aggregate="mean", message_init="zero")
    got, zn, un, an = field_at_random_point(net, seed=2)
    expected = np.zeros_like(zn)
    for b in range(2):
        for i in range(4):
            x_i, m = zn[b, i, :D], zn[b, :, D:]
            senders = in_neighbours(an[b], i)
            m_bar = m[senders].mean(axis=0) if len(senders) else np.zeros(M)
            expected[b, i] = mlp_np(net.net, np.concatenate([x_i, un[b, i], m_bar]))
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)
    assert not in_neighbours(an[0], 3).size and not in_neighbours(an[1], 0).size

    x0 = torch.from_numpy(zn[..., :D])
    torch.testing.assert_close(net.initial_state(x0, torch.from_numpy(un)),  # m(t₀) = 0
                               torch.cat([x0, torch.zeros(2, 4, M)], dim=-1))


def test_mpnode_affine_update_is_its_documented_formula():
    # mpnode.py's docstring, with the gains laid out row-major in the MLP's output
    # [F (D+M), G_x (D·M), G_m (M·M)] and ψ the sender's MLP of [x_j, u_j, m_j]:
    #   ẋ_i = F_x(x_i, u_i) + G_x(x_i, u_i) · Σ_j ψ_j
    #   ṁ_i = F_m(x_i, u_i) + G_m(x_i, u_i) · mean_j ψ_j
    net = mpnode(update="affine", aggregate="sum")
    got, zn, un, an = field_at_random_point(net, seed=3)
    expected = np.zeros_like(zn)
    for b in range(2):
        psi = np.stack([mlp_np(net.emit, np.concatenate([zn[b, j, :D], un[b, j], zn[b, j, D:]]))
                        for j in range(4)])  # (N, M): what each node sends
        for i in range(4):
            out = mlp_np(net.net, np.concatenate([zn[b, i, :D], un[b, i]]))
            f, g_x, g_m = np.split(out, [D + M, D + M + D * M])
            senders = in_neighbours(an[b], i)
            total = psi[senders].sum(axis=0)
            mean = total / len(senders) if len(senders) else np.zeros(M)
            expected[b, i, :D] = f[:D] + g_x.reshape(D, M) @ total
            expected[b, i, D:] = f[D:] + g_m.reshape(M, M) @ mean
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("given", ["none", "wrong U"])
def test_every_ode_model_refuses_missing_or_mismatched_controls_alike(given):
    errors = []
    for kind in ODE_KINDS:
        torch.manual_seed(0)
        net = build_model(kind, {"node_dim": 2, "control_dim": 2, "num_nodes": 3})
        controls = None if given == "none" else torch.zeros(1, 4, 3, 3)
        with pytest.raises(ValueError, match="expects 2 controls per node") as info:
            net.rollout(torch.zeros(1, 3, 2), torch.arange(4) * 0.1, torch.ones(1, 3, 3),
                        controls)
        errors.append(str(info.value))
    assert len(set(errors)) == 1, errors  # one message, from the one rollout


def test_neural_model_is_abstract_without_a_rollout():
    class Bare(NeuralModel):
        kind = "bare"
        Options = ModelOptions

    with pytest.raises(TypeError, match="abstract"):
        Bare(2)
    with pytest.raises(TypeError, match="abstract"):
        NeuralModel(2)

    class NoField(NeuralODEModel):
        kind = "no-field"
        Options = ModelOptions

    with pytest.raises(TypeError, match="abstract"):
        NoField(2)


def test_the_ode_models_share_one_rollout_and_one_vector_field_signature():
    for cls in (MPNODE, GNODE, NODE):
        assert issubclass(cls, NeuralODEModel)
        assert "rollout" not in vars(cls), cls
        assert list(inspect.signature(cls.vector_field).parameters) == ["self", "adjacency",
                                                                         "u"]
    assert MPNODE.rollout is GNODE.rollout is NODE.rollout is NeuralODEModel.rollout
    assert issubclass(L2S, NeuralModel) and not issubclass(L2S, NeuralODEModel)


def scipy_rollout(net: NeuralODEModel, x0, ts, adjacency, controls) -> torch.Tensor:
    """z at every sample `[B, T, N, D+M]`: scipy's DOP853 on the model's vector field, one
    solve per sample interval with that interval's control held constant."""
    z = net.initial_state(x0, controls[:, 0])
    out = [z]
    for k in range(len(ts) - 1):
        f = net.vector_field(adjacency, lambda t, held=controls[:, k]: held)

        def rhs(t, y, f=f, shape=z.shape):
            return f(torch.full((shape[0],), t), torch.from_numpy(y).view(shape)).numpy().ravel()

        sol = solve_ivp(rhs, (float(ts[k]), float(ts[k + 1])), z.numpy().ravel(),
                        method="DOP853", rtol=1e-11, atol=1e-12)
        z = torch.from_numpy(sol.y[:, -1]).view(z.shape)
        out.append(z)
    return torch.stack(out, dim=1)


@pytest.mark.parametrize("kind", ODE_KINDS)
def test_the_rollout_integrates_the_vector_field_under_held_controls(kind):
    torch.manual_seed(0)
    options = {"message_init": "learned"} if kind == "mpnode" else {}
    net = build_model(kind, {"node_dim": D, "control_dim": U, "num_nodes": 4, "hidden": 6,
                             **options})
    gen = torch.Generator().manual_seed(4)
    x0 = torch.randn(2, 4, D, generator=gen)
    ts = torch.linspace(0.0, 0.8, 5, dtype=torch.float64)
    controls = torch.ones(2, 5, 4, U)
    controls[1, 2:] = -1.5  # one switch, at ts[2]
    adjacency = directed_graphs()
    with torch.no_grad():
        out = net.rollout(x0, ts, adjacency, controls, return_messages=True,
                          solver=SolverOptions(rtol=1e-10, atol=1e-10))
        ref = scipy_rollout(net, x0, ts, adjacency, controls)
    torch.testing.assert_close(out.states, ref[..., :D], rtol=1e-7, atol=1e-8)
    if kind == "mpnode":
        torch.testing.assert_close(out.messages, ref[..., D:], rtol=1e-7, atol=1e-8)
    else:
        assert out.messages is None and ref.shape[-1] == D
