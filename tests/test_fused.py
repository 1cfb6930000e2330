"""The hand-written MLP backward against autograd and finite differences."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from mpnode_cli.models.base import mlp
from mpnode_cli.models.fused import FusedMLP


def _plain(net: FusedMLP) -> nn.Sequential:
    """The same layers as an ordinary `nn.Sequential` (autograd records every op)."""
    return nn.Sequential(*net)


@pytest.mark.parametrize("activation", ["tanh", "relu"])
@pytest.mark.parametrize("layers", [1, 2, 3])
def test_values_and_gradients_match_autograd(activation, layers):
    torch.manual_seed(0)
    net = mlp(5, 7, layers, 4, activation).double()
    assert net._fused
    x = torch.randn(3, 6, 5, dtype=torch.float64, requires_grad=True)
    g = torch.randn(3, 6, 4, dtype=torch.float64)

    out = net(x)
    grads = torch.autograd.grad(out, [x, *net.parameters()], g)
    ref_out = _plain(net)(x)
    ref = torch.autograd.grad(ref_out, [x, *net.parameters()], g)
    assert out.shape == ref_out.shape == (3, 6, 4)
    torch.testing.assert_close(out, ref_out, rtol=1e-12, atol=1e-12)
    for a, b in zip(grads, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_gradcheck_against_finite_differences():
    torch.manual_seed(1)
    net = mlp(3, 4, 2, 2, "tanh").double()
    x = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    params = list(net.parameters())
    # Perturb each parameter too: the check covers dW and db as well as dx.
    names = [name for name, _ in net.named_parameters()]

    def f(x, *ps):
        state = dict(zip(names, ps, strict=True))
        return torch.func.functional_call(net, state, (x,))

    assert torch.autograd.gradcheck(f, (x, *[p.detach().requires_grad_() for p in params]))


def test_no_input_gradient_when_the_input_does_not_need_one():
    net = mlp(3, 4, 2, 2, "tanh")
    out = net(torch.randn(8, 3))
    out.sum().backward()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in net.parameters())


def test_other_activations_take_the_plain_path_and_state_dicts_are_interchangeable():
    net = mlp(3, 4, 2, 2, "silu")
    assert not net._fused
    fused = mlp(3, 4, 2, 2, "tanh")
    plain = _plain(fused)
    assert list(fused.state_dict()) == list(plain.state_dict()) == [
        "0.weight", "0.bias", "2.weight", "2.bias", "4.weight", "4.bias"]
