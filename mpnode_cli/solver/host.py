"""The adaptive loop's small arithmetic, written once, run in torch or in numpy.

Besides the stages' work on `[B, F]` states, each adaptive step plans its size, controls its
error, keeps its books and weighs its dense outputs (`adaptive.plan_step`, `control`,
`dense_weights`, and the first step's `initial_step`): ~60 ops, most on `[B]` vectors. On
the CPU, a torch op that small costs 1–4 µs of dispatch and the same numpy op 0.3–1 µs,
while `Tensor.numpy()` and `torch.from_numpy` share memory with no copy. So that code is
written against an array namespace, `TorchOps` or `NumpyOps`, which the solve picks once
(`ops_for`): numpy for an uncompiled solve on the CPU, torch on CUDA (numpy would need a
copy and a sync) and under `compile` (the compiled step is tensor code). The step-size
controllers (`controller.py`) take the same namespace.

A function takes its tensors in through `arrays` (detached numpy views, or the tensors
themselves) and hands its results out through `tensors`, so the loop's `State` holds
tensors either way. Both namespaces compute the same thing in the same dtypes: float64
time, step sizes and error ratios, int64 counters, bool masks. They take the same steps bit
for bit: numpy's arithmetic, comparisons and selections round as torch's do, and the two
ops that round otherwise in numpy (`pow`, and the sums of squares of the error norm) are
torch's on numpy's memory. Only the dense outputs' weights b_i(θ) and, where autograd does
not record the step, their sums y + Σ b_i(θ)·h·k_i (`lanes`) are numpy's, and agree with
torch's to rounding; the step never reads them back.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import torch

# Tests and bench/ set this to False to run the torch namespace on the CPU too, and compare.
NUMPY_ON_CPU = True


class TorchOps:
    """The torch namespace: tensors in, tensors out, torch's ops (on any device, and
    traceable by `torch.compile`)."""

    where = staticmethod(torch.where)
    minimum = staticmethod(torch.minimum)
    maximum = staticmethod(torch.maximum)
    take = staticmethod(torch.take)  # a[i] for any shape of i, a flat
    pow = staticmethod(torch.pow)
    no_grad = torch.no_grad

    @staticmethod
    def arrays(*xs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return xs

    @staticmethod
    def tensors(*xs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return xs

    @staticmethod
    def clip(x, lo=None, hi=None):
        return torch.clamp(x, lo, hi)

    @staticmethod
    def astype(x, like):
        """x in `like`'s dtype."""
        return x.to(like.dtype)

    @staticmethod
    def rms(x):
        """`[B, F]` → `[B]` root mean square over each row, in float64 (the norm itself in
        x's dtype)."""
        return torch.linalg.vector_norm(x, dim=1).double() / math.sqrt(x.shape[1])

    @staticmethod
    def searchsorted(a, v):
        """For each v, the number of entries of the sorted a that are ≤ v."""
        return torch.searchsorted(a, v, right=True)

    @staticmethod
    def interpolant(theta, interp_t):
        """`[B, W, s]` b_i(θ) at `theta [B, W]`, b(θ) = [θ, θ², ..., θ^K] @ interp_t.T."""
        k_max = interp_t.shape[1]
        powers = theta[..., None].expand(-1, -1, k_max).cumprod(-1)  # (B, W, K): θ, ..., θ^K
        # (s, K) @ (K, B·W): the long side last, twice as fast as (B·W, K) @ (K, s).
        coef = (interp_t @ powers.view(-1, k_max).T).view(-1, *theta.shape)  # (s, B, W)
        return coef.permute(1, 2, 0)

    @staticmethod
    def lanes(coef, hk, y):
        """`[B, W, F]` tensor, the dense-output lanes y + Σ_i coef[b, w, i]·hk[i, b], as the
        recorded step computes them (differentiable).

        Args: coef `[B, W, s]`; hk `[s, B, F]` the stages h·k_i; y `[B, F]`.
        """
        return y.unsqueeze(1) + torch.einsum("bwi,ibf->bwf", coef, hk)

    @staticmethod
    def write_lanes(out, rows, coef, hk, y):
        """`out[rows] = lanes(coef, hk, y)` (`out`: `[R, F]`, rows `[B·W]` int64), in place,
        outside autograd; equal to `lanes` bit for bit."""
        # (B, s, F): a sample-major copy of the stages, against bmm's slow path for a
        # batch stride smaller than the row stride (measured: ~0.1 ms a training step).
        values = torch.bmm(coef, hk.transpose(0, 1).contiguous())  # (B, W, F)
        values += y[:, None]
        out.index_copy_(0, rows, values.view(-1, out.shape[1]))

    @staticmethod
    def flags(*xs):
        """One int64 array of each `[B]` array's max (a bool's any) and any scalars after
        them: what the loop reads in its one sync (`.tolist()`)."""
        # One stack and one amax (type promotion makes the bools 0/1), against a reduction
        # per vector and a stack of their results.
        vectors = [x for x in xs if x.ndim]
        flags = torch.stack(vectors).amax(1)
        scalars = [x.view(1) for x in xs if not x.ndim]
        return torch.cat([flags, *scalars]) if scalars else flags


class NumpyOps:
    """The numpy namespace for CPU tensors: numpy views in, numpy's ops, zero-copy tensors
    out."""

    where = staticmethod(np.where)
    minimum = staticmethod(np.minimum)
    maximum = staticmethod(np.maximum)
    take = staticmethod(np.take)
    no_grad = contextlib.nullcontext  # numpy records nothing

    @staticmethod
    def arrays(*xs: torch.Tensor) -> list[np.ndarray]:
        return [x.detach().numpy() if x.requires_grad else x.numpy() for x in xs]

    @staticmethod
    def tensors(*xs: np.ndarray) -> list[torch.Tensor]:
        return [torch.from_numpy(x) for x in xs]

    @staticmethod
    def clip(x, lo=None, hi=None):
        # np.clip checks its arguments in Python (~1.5 µs); these are two ufunc calls.
        if lo is not None:
            x = np.maximum(x, lo)
        return x if hi is None else np.minimum(x, hi)

    @staticmethod
    def astype(x, like):
        return x.astype(like.dtype)

    # Two of torch's ops on numpy's memory, so that both namespaces take the same steps bit
    # for bit: numpy's pow (libm's) and its sums of squares (another order) round
    # differently from torch's in the last bit, and an error estimate, which cancels, turns
    # that into step sizes that differ at 1e-8 (outputs at 1e-11 at rtol 1e-5). Each costs
    # ~2 µs more than numpy's.
    @staticmethod
    def rms(x):
        return TorchOps.rms(torch.from_numpy(x)).numpy()

    @staticmethod
    def pow(x, e):
        return torch.from_numpy(x).pow(e).numpy()

    @staticmethod
    def searchsorted(a, v):
        return np.searchsorted(a, v, side="right")

    @staticmethod
    def interpolant(theta, interp_t):
        x = theta.reshape(-1)
        # (K, B·W): θ, ..., θ^K, a power a row, each the row above times θ (cumprod's
        # products; numpy's cumprod along a short last axis took ~30 µs for 256 rows).
        powers = np.empty((interp_t.shape[1], x.size))
        powers[0] = x
        for k in range(1, powers.shape[0]):
            np.multiply(powers[k - 1], x, out=powers[k])
        # (B·W, K) @ (K, s): one product, already in the (B, W, s) layout.
        return (powers.T @ interp_t.T).reshape(*theta.shape, -1)

    @staticmethod
    def lanes(coef, hk, y):
        """Not differentiable: for a step that autograd does not record."""
        coef, hk, y = NumpyOps.arrays(coef, hk, y)
        return torch.from_numpy(_lanes(coef, hk, y))

    @staticmethod
    def write_lanes(out, rows, coef, hk, y):
        out, rows, coef, hk, y = NumpyOps.arrays(out, rows, coef, hk, y)
        out[rows] = _lanes(coef, hk, y).reshape(-1, out.shape[1])

    @staticmethod
    def flags(*xs):
        return np.array([x.max() if x.ndim else x for x in xs], dtype=np.int64)


def _lanes(coef: np.ndarray, hk: np.ndarray, y: np.ndarray) -> np.ndarray:
    """`NumpyOps.lanes`' arrays."""
    # One small product per sample on the strided (B, s, F) view of the stages, with no
    # copy: against torch's copy and bmm, measured 5× faster for one lane a sample
    # (B = 512, F = 30, float64) and 1.4× for 13 (B = 128, F = 18, float32).
    values = np.matmul(coef, hk.transpose(1, 0, 2))  # (B, W, F)
    values += y[:, None]
    return values


Ops = type[TorchOps] | type[NumpyOps]


def ops_for(device: torch.device, compile: bool) -> Ops:
    """The namespace of a solve on `device`: numpy on the CPU uncompiled, else torch."""
    return NumpyOps if NUMPY_ON_CPU and device.type == "cpu" and not compile else TorchOps
