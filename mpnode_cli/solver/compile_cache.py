"""`CompileCache`: functions compiled by `torch.compile` once for as long as the cache lives,
with an eager fallback that, once taken, holds for the rest of its life.

Torch is imported on the first compiled call only, so that `options.py` (which keeps one
cache per `SolverOptions`) imports without it.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any


class CompileCache:
    """Calls a function compiled (inductor), or as it is once a compile has failed.

    `torch.compile` caches a graph per right-hand side, shape and grad mode, but only for
    the wrapper that made it: a new wrapper of the same function compiles again. This
    object makes the wrapper once per function, so every solve given the same cache shares
    those graphs (a solve with `compile=True` makes one of its own; `SolverOptions` keeps
    one for every solve run with it). A compile that fails (no C++ compiler, an
    unsupported op, ...) warns once, and every later call runs the function eagerly, which
    computes the same thing.

    Attributes:
        compiled: each function's compiled wrapper, made on its first call.
        failed: whether a compiled call has failed.
    """

    def __init__(self) -> None:
        self.compiled: dict[Callable[..., Any], Callable[..., Any]] = {}
        self.failed = False

    def __call__(self, fn: Callable[..., Any], *args: Any) -> Any:
        """`fn(*args)`, compiled unless a compiled call has failed before."""
        if self.failed:
            return fn(*args)
        step = self._compiled(fn)
        try:
            return step(*args)
        except Exception as exc:  # any compiler failure: run eagerly (fn's own errors recur)
            self._fail(exc)
        return fn(*args)

    # A cache is not part of the value of what holds it: any two are equal (two equal
    # `SolverOptions` compare equal), and a copy or a pickle starts empty (a compiled
    # wrapper can be neither; another process compiles anew).
    def __eq__(self, other: object) -> bool:
        return isinstance(other, CompileCache)

    def __hash__(self) -> int:
        return hash(CompileCache)

    def __reduce__(self) -> tuple[type[CompileCache], tuple[()]]:
        return CompileCache, ()

    def _compiled(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """`fn`'s wrapper, made once. Automatic dynamic shapes (`dynamic=None`): a second
        size of a dimension (a horizon curriculum's next horizon, a smaller last batch)
        recompiles once with that dimension symbolic, and every later size reuses it,
        instead of one compile per size up to the cache limit."""
        if fn not in self.compiled:
            import torch
            import torch._dynamo.config as dynamo_config

            # Compiling traces the step's backward under autograd's anomaly mode, which
            # prints the forward's stack as a UserWarning when anything stops that trace: a
            # Ctrl-C or SIGTERM during the first epochs (the interrupt itself is reported as
            # usual), or a compiler failure (which `_fail` reports in one line).
            warnings.filterwarnings("ignore", message="Error detected in ",
                                    category=UserWarning, module="torch.autograd.graph")
            # One process may train several models (an experiment's steps, run one after
            # another): each new node count, batch layout or grad mode adds a variant of the
            # step, and past dynamo's default of 8 every further one would run eagerly, with
            # a warning, for the rest of the process (seen: a gene 4×4 training, then its
            # 8×8 finetune). Each variant compiles once, so a higher cap costs only those
            # compiles.
            dynamo_config.recompile_limit = max(dynamo_config.recompile_limit, 64)
            self.compiled[fn] = torch.compile(fn, dynamic=None)
        return self.compiled[fn]

    def _fail(self, exc: Exception) -> None:
        """Warn once (in one line) that compiling failed; run eagerly from now on."""
        if not self.failed:
            text = str(exc).strip()
            first = text.splitlines()[0] if text else type(exc).__name__
            # stacklevel: _fail ← __call__ ← the steps' `attempt` ← the solver's loop.
            warnings.warn(f"torch.compile of the solver step failed ({first[:200]}); "
                          "running it uncompiled", RuntimeWarning, stacklevel=4)
        self.failed = True
