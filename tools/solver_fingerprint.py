"""Fingerprint the solver's numbers: SHA-256 of every tensor a matrix of solves returns.

A refactoring of `mpnode_cli/solver/` that is meant to change no number runs this before
and after, and compares: every hash the same means every output, statistic, status and
gradient the same bit for bit.

The matrix: every method of `solver/tableau.py`; adaptive (both controllers, plain and
with a tstop and compaction, from Hairer's first step and from a given `dt0`, and one
that runs out of steps) and fixed steps (with and without a tstop); fused and recorded
steps; float64 and float32. Each solve runs twice: recorded by autograd, with a backward
pass (gradients with respect to y0, a shared parameter and a per-sample one), and under
`torch.no_grad` (the untracked dense outputs). The batch holds slow samples, fast
oscillating ones (so that compaction drops the slow ones) and one that blows up (a
failing sample: its status and the NaN outputs after it).

Usage:
    PYTHONPATH=$PWD python tools/solver_fingerprint.py out.json [--tensors out.pt]
        [--compile]
    PYTHONPATH=$PWD python tools/solver_fingerprint.py --compare a.json b.json
`--tensors` also saves the tensors themselves (to measure a difference that a hash only
flags); `--compile` adds a solve through `torch.compile` (~1 min). `--compare` prints the
entries that differ and exits 1 if any does.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections.abc import Iterator

import torch

from mpnode_cli.solver import solve
from mpnode_cli.solver.tableau import METHODS

SWITCH = 0.37  # where the field's zero-order-hold input jumps (the tstop)
T_EVAL = [0.0, 0.1, 0.25, 0.5, 0.8, 1.0]
N_SLOW, N_FAST = 16, 7  # and one sample that blows up


def problem(dtype: torch.dtype, fail: bool = True):
    """`(y0 [B, 3, 2], theta [2], rate [B], omega [B], quad [B])`, the last three
    per-sample: decay rate, angular frequency, and the quadratic term of the last sample,
    which (`fail`) blows up near t = 1/3. y0, theta and rate require gradients."""
    gen = torch.Generator().manual_seed(0)
    batch = N_SLOW + N_FAST + 1
    y0 = torch.randn(batch, 3, 2, generator=gen, dtype=torch.float64)
    if fail:
        y0[-1] = 3.0
    rate = 0.2 + torch.rand(batch, generator=gen, dtype=torch.float64)
    omega = torch.cat([torch.rand(N_SLOW, generator=gen, dtype=torch.float64),
                       12.0 + 6.0 * torch.rand(N_FAST, generator=gen, dtype=torch.float64),
                       torch.zeros(1, dtype=torch.float64)])
    quad = torch.zeros(batch, dtype=torch.float64)
    quad[-1] = 1.0 if fail else 0.0
    theta = torch.tensor([0.7, -0.4], dtype=torch.float64)
    leaves = [x.to(dtype).requires_grad_() for x in (y0, theta, rate)]
    return (*leaves, omega.to(dtype), quad.to(dtype))


def field(theta, rate, omega, quad):
    """The right-hand side on `[B, 3, 2]` states with the per-sample arrays given."""

    def f(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        x, v = y[..., 0], y[..., 1]  # (B, 3) each
        u = torch.where(t < SWITCH, 1.0, -2.0).to(y.dtype)[:, None]
        cos_t = torch.cos(t).to(y.dtype)[:, None]
        k, w, c = rate[:, None], omega[:, None], quad[:, None]
        dx = w * v - k * x + c * x * x + theta[0] * u * cos_t
        dv = -w * x - k * v + theta[1] * torch.sin(x.roll(1, dims=1))
        return torch.stack([dx, dv], dim=-1)

    return f


def cases(compile: bool) -> Iterator[tuple[str, dict]]:
    """`(name, solve's keyword arguments)` of the matrix."""
    for method, tableau in METHODS.items():
        for fused in (True, False):
            # A fixed step does not stop a sample before it blows up, whose NaN then
            # reaches the shared parameter's gradient: the failing sample with the tstop only.
            for tstop in (False, True):
                yield (f"{method}/fixed/fused={fused}/tstop={tstop}",
                       dict(method=method, fixed_dt=0.04, fused=fused, fail=tstop,
                            tstops=[SWITCH] if tstop else None))
            if tableau.e is None:
                continue
            for ctrl in ("pi", "i"):
                for extra in ("plain", "tstop+compact", "dt0")[: 3 if ctrl == "pi" else 2]:
                    kw = dict(method=method, controller=ctrl, fused=fused, rtol=1e-5,
                              atol=1e-7)
                    if extra == "tstop+compact":
                        kw |= dict(tstops=[SWITCH], restrict=True)
                    elif extra == "dt0":
                        kw |= dict(dt0=1e-3)
                    yield f"{method}/adaptive/{ctrl}/fused={fused}/{extra}", kw
            yield (f"{method}/adaptive/max_steps/fused={fused}",
                   dict(method=method, fused=fused, max_steps=40, tstops=[SWITCH]))
            if method == "tsit5":
                yield f"{method}/adaptive/defaults/fused={fused}", dict(fused=fused)
    if compile:
        yield "tsit5/adaptive/pi/compiled", dict(compile=True, tstops=[SWITCH])


def run(kw: dict, dtype: torch.dtype, grad: bool) -> dict[str, torch.Tensor]:
    """The tensors of one solve: ys, status, stats and (with `grad`) the gradients."""
    kw = dict(kw)
    y0, theta, rate, omega, quad = problem(dtype, kw.pop("fail", True))
    if kw.pop("restrict", False):
        kw["restrict"] = lambda index: field(theta, rate[index], omega[index], quad[index])
    with torch.set_grad_enabled(grad):
        sol = solve(field(theta, rate, omega, quad), y0, T_EVAL, **kw)
    got = {"ys": sol.ys.detach(), "status": sol.status,
           **{f"stats.{k}": v for k, v in sol.stats.items()}}
    if grad:
        weights = torch.linspace(-1.0, 2.0, sol.ys[0].numel(), dtype=dtype).view(sol.ys[0].shape)
        loss = (torch.where(torch.isfinite(sol.ys), sol.ys, 0.0) * weights).sum()
        grads = torch.autograd.grad(loss, (y0, theta, rate))
        got |= {"grad.y0": grads[0], "grad.theta": grads[1], "grad.rate": grads[2]}
    return got


def sha(x: torch.Tensor) -> str:
    x = x.detach().cpu().contiguous()
    head = f"{x.dtype}{tuple(x.shape)}".encode()
    return hashlib.sha256(head + x.numpy().tobytes()).hexdigest()


def fingerprint(compile: bool, only: str = "") -> tuple[dict[str, str], dict[str, torch.Tensor]]:
    """`(hashes, tensors)`, keyed `case/dtype/grad-or-nograd/tensor`, of the cases whose
    name contains `only`."""
    hashes, tensors = {}, {}
    for name, kw in cases(compile):
        if only not in name:
            continue
        for dtype in (torch.float64, torch.float32):
            for grad in (True, False):
                key = f"{name}/{str(dtype)[6:]}/{'grad' if grad else 'nograd'}"
                for k, v in run(kw, dtype, grad).items():
                    hashes[f"{key}/{k}"] = sha(v)
                    tensors[f"{key}/{k}"] = v.detach().cpu()
    return hashes, tensors


def compare(a_path: str, b_path: str) -> int:
    a, b = (json.load(open(p)) for p in (a_path, b_path))
    both = a.keys() & b.keys()  # a fingerprint of some cases (`--only`) against all
    differ = sorted(k for k in both if a[k] != b[k])
    for k in differ:
        print(f"differs: {k}")
    print(f"{len(differ)} of {len(both)} shared entries differ "
          f"({len(a.keys() ^ b.keys())} in one only)")
    return 1 if differ else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", help="JSON file of the hashes to write")
    parser.add_argument("--tensors", help="also save the tensors (torch.save) here")
    parser.add_argument("--compile", action="store_true", help="add a compiled solve")
    parser.add_argument("--only", default="", help="only the cases whose name contains this "
                        "(e.g. tsit5/adaptive), for a quick look")
    parser.add_argument("--compare", nargs=2, metavar="JSON", help="compare two fingerprints")
    args = parser.parse_args(argv)
    if args.compare:
        return compare(*args.compare)
    if not args.out:
        parser.error("give the JSON file to write, or --compare A B")
    torch.manual_seed(0)
    hashes, tensors = fingerprint(args.compile, args.only)
    with open(args.out, "w") as fh:
        json.dump(hashes, fh, indent=1, sort_keys=True)
    if args.tensors:
        torch.save(tensors, args.tensors)
    print(f"{len(hashes)} tensors hashed into {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
