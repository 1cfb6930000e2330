"""An MLP whose forward and backward are written by hand: one autograd node per call.

MP-NODE's vector field is a small MLP (2 × 32, tanh) evaluated at every stage of every solver
step, on a few hundred rows. At that size a training step is bound by per-operation overhead
rather than arithmetic: autograd records each linear layer as several nodes (transpose,
matmul, bias, view) and runs each one through its engine. `FusedMLP` computes the same
function with one `addmm` and one activation per layer and records one node for the whole
network, whose backward is the textbook chain rule: for each layer from the last,

    dW = gᵀ a_in,  db = Σ_rows g,  g_in = (g W) ⊙ σ'(pre-activation),

with σ' taken from the layer's *output* (tanh: 1 − y²; relu: y > 0), so only the layer
inputs are kept. Activations whose derivative needs the input (elu, silu, softplus) use
the ordinary module path. The parameters are those of the `nn.Sequential` it subclasses
(keys `0.weight`, `0.bias`, `2.weight`, …), so checkpoints are interchangeable with it.
tests/test_fused.py checks values and gradients against autograd and finite differences.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.autograd.function import once_differentiable

# Activations whose derivative is a function of the output: name → (forward, backward).
_FROM_OUTPUT = {
    nn.Tanh: (torch.tanh, torch.ops.aten.tanh_backward),
    nn.ReLU: (torch.relu, lambda g, y: torch.ops.aten.threshold_backward(g, y, 0)),
}


class _MLPFunction(torch.autograd.Function):
    """`x [R, in]`, then (W, b) per layer → `[R, out]`; activation after all but the last."""

    @staticmethod
    def forward(ctx, x, act, act_grad, *params):
        weights, biases = params[0::2], params[1::2]
        inputs = []
        a = x
        last = len(weights) - 1
        for k, (w, b) in enumerate(zip(weights, biases, strict=True)):
            inputs.append(a)
            a = torch.addmm(b, a, w.t())
            if k < last:
                a = act(a)
        ctx.act_grad = act_grad
        ctx.save_for_backward(*inputs, *weights)
        return a

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        saved = ctx.saved_tensors
        n = len(saved) // 2
        inputs, weights = saved[:n], saved[n:]
        need = ctx.needs_input_grad  # (x, act, act_grad, W0, b0, W1, b1, ...)
        grads: list[torch.Tensor | None] = [None] * (2 * n)
        g = grad
        for k in range(n - 1, -1, -1):
            a_in, w = inputs[k], weights[k]
            if need[3 + 2 * k]:
                grads[2 * k] = g.t().mm(a_in)
            if need[4 + 2 * k]:
                grads[2 * k + 1] = g.sum(0)
            if k == 0 and not need[0]:
                g = None
                break
            g = g.mm(w)
            if k > 0:
                g = ctx.act_grad(g, a_in)  # a_in is layer k−1's activation output
        return (g, None, None, *grads)


class FusedMLP(nn.Sequential):
    """`nn.Sequential` of Linear / activation / … / Linear with a hand-written backward.

    Any leading dimensions are flattened into rows; the result has the input's leading
    shape. Falls back to the plain sequential forward for activations not in
    `_FROM_OUTPUT` or for layer lists of another shape.
    """

    def __init__(self, *modules: nn.Module):
        super().__init__(*modules)
        linears = list(modules[0::2])
        acts = list(modules[1::2])
        kinds = {type(a) for a in acts}
        self._fused = (
            all(isinstance(m, nn.Linear) for m in linears)
            and len(kinds) == 1 and next(iter(kinds)) in _FROM_OUTPUT
        )
        if self._fused:
            self._act, self._act_grad = _FROM_OUTPUT[next(iter(kinds))]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self._fused:
            return super().forward(x)
        lead = x.shape[:-1]
        params = [p for m in self[0::2] for p in (m.weight, m.bias)]
        out = _MLPFunction.apply(x.reshape(-1, x.shape[-1]), self._act, self._act_grad,
                                 *params)
        return out.view(*lead, out.shape[-1])
