"""The dense output's numpy form against its torch form, on the CPU, in one process.

An uncompiled CPU solve weighs its dense outputs, and where autograd does not record the
step sums them, in numpy (`mpnode_cli/solver/dense.py`); `dense.NUMPY_ON_CPU = False` takes
torch's form instead. The rest of the step (its plan, error control and bookkeeping) is
torch in both: it ran in numpy too until that was measured here to save nothing (0.99× on
the training step, 0.87× on the Lorenz solve). Both take the same steps bit for bit, so this
measures only what numpy saves. Each round runs one call of each variant, in random order,
and times it in thread CPU time and wall time; reported is the median of the per-round
ratios numpy / torch (below 1: numpy faster), with a bootstrap 95% interval of that median.
Interleaving one call at a time keeps the comparison fair on a machine busy with other work,
where bare times are not.

Problems:
- `fwd`: the training step of `bench/train.py` (MP-NODE, B = 128, float32, tsit5,
  rtol = atol = 1e-4, the integral controller), its forward under `torch.no_grad`;
- `fwdgrad`: the same forward recorded by autograd, and its loss;
- `step`: the whole training step, forward and backward;
- `lorenz`: the coupled Lorenz systems of `bench/solver.py`, B = 512, float64,
  rtol 1e-6, atol 1e-8 (no gradients).

Usage:
    .venv/bin/python bench/host_ops.py [fwd fwdgrad step lorenz] [--rounds 400]   # ~1 min
Prints one line per problem; writes nothing.
"""

from __future__ import annotations

import argparse
import random
import sys
import time

import numpy as np
import torch

from mpnode_cli.solver import dense, solve

PROBLEMS = ["fwd", "fwdgrad", "step", "lorenz"]


def compare(name: str, fn, rounds: int) -> None:
    """Time `fn` with the numpy and the torch namespace, interleaved; print the ratios."""
    for flag in (False, True) * 3:  # warm up both
        dense.NUMPY_ON_CPU = flag
        fn()
    cpu, wall, times = [], [], {False: [], True: []}
    order = [False, True]
    rng = random.Random(0)
    try:
        for _ in range(rounds):
            rng.shuffle(order)
            got = {}
            for flag in order:
                dense.NUMPY_ON_CPU = flag
                c0, w0 = time.thread_time(), time.perf_counter()
                fn()
                got[flag] = (time.thread_time() - c0, time.perf_counter() - w0)
                times[flag].append(got[flag][0])
            cpu.append(got[True][0] / got[False][0])
            wall.append(got[True][1] / got[False][1])
    finally:
        dense.NUMPY_ON_CPU = True
    boot = np.random.default_rng(0)
    lo, hi = np.percentile([np.median(boot.choice(cpu, len(cpu))) for _ in range(2000)],
                           [2.5, 97.5])
    print(f"{name:34s} numpy/torch: CPU time {np.median(cpu):.3f} (95% {lo:.3f}–{hi:.3f}), "
          f"wall {np.median(wall):.3f}; median CPU ms torch {1e3 * np.median(times[False]):.2f}"
          f", numpy {1e3 * np.median(times[True]):.2f}; {rounds} rounds", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problems", nargs="*", metavar="PROBLEM",
                        help=f"any of {', '.join(PROBLEMS)} (default: all)")
    parser.add_argument("--rounds", type=int, default=400,
                        help="rounds of the training step (twice as many of its forward, "
                        "a twentieth of the Lorenz solve)")
    args = parser.parse_args(argv)
    if unknown := set(args.problems) - set(PROBLEMS):
        parser.error(f"unknown problem {', '.join(sorted(unknown))}")
    args.problems = args.problems or PROBLEMS
    torch.set_num_threads(1)
    if {"fwd", "fwdgrad", "step"} & set(args.problems):
        from train import StepProblem

        problem = StepProblem()

        def forward():
            with torch.no_grad():
                problem.states("mpnode tsit5")

        def recorded():
            problem.model.zero_grad(set_to_none=True)
            states, _ = problem.states("mpnode tsit5")
            torch.nn.functional.mse_loss(states, problem.target)

        if "fwd" in args.problems:
            compare("training step's forward, no grad", forward, 2 * args.rounds)
        if "fwdgrad" in args.problems:
            compare("training step's forward, recorded", recorded, 2 * args.rounds)
        if "step" in args.problems:
            compare("training step", lambda: problem.step("mpnode tsit5"), args.rounds)
    if "lorenz" in args.problems:
        from solver import DT_SAVE, N_NODES, T_END, coupling, torch_rhs

        ts = torch.tensor(np.arange(0.0, T_END + DT_SAVE / 2, DT_SAVE), dtype=torch.float64)
        y0 = torch.tensor(np.random.default_rng(1).uniform(-1, 1, size=(512, 3 * N_NODES)),
                          dtype=torch.float64)
        f = torch_rhs(coupling(), torch.float64)
        compare("coupled Lorenz, B = 512, float64", lambda: solve(f, y0, ts, rtol=1e-6,
                                                                   atol=1e-8),
                max(args.rounds // 20, 10))
    return 0


if __name__ == "__main__":
    sys.exit(main())
