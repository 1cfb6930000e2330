"""`CompileCache`: a function compiled by `torch.compile` once per process, with an eager
fallback that, once taken, holds for the rest of the process."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any

import torch


class CompileCache:
    """Calls `fn` either compiled (inductor) or as it is.

    `torch.compile` caches a graph per right-hand side, shape and grad mode; this object
    makes the compiled wrapper once, so every solve of the process shares those graphs.
    A compile that fails (no C++ compiler, an unsupported op, ...) warns once, and every
    later call runs `fn` eagerly, which computes the same thing.

    Attributes:
        fn: the function, run as it is when compiling is off or has failed.
        compiled: its compiled wrapper, made on the first compiled call (None before).
        failed: whether a compiled call has failed in this process.
    """

    def __init__(self, fn: Callable[..., Any]):
        self.fn = fn
        self.compiled: Callable[..., Any] | None = None
        self.failed = False

    def __call__(self, compile: bool, *args: Any) -> Any:
        """`fn(*args)`, compiled if `compile` and no compiled call has failed before."""
        if not compile or self.failed:
            return self.fn(*args)
        step = self._compiled()
        try:
            return step(*args)
        except Exception as exc:  # any compiler failure: run eagerly (fn's own errors recur)
            self._fail(exc)
        return self.fn(*args)

    def _compiled(self) -> Callable[..., Any]:
        """The wrapper, made once. Automatic dynamic shapes (`dynamic=None`): a second size
        of a dimension (a horizon curriculum's next horizon, a smaller last batch) recompiles
        once with that dimension symbolic, and every later size reuses it, instead of one
        compile per size up to the cache limit."""
        if self.compiled is None:
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
            self.compiled = torch.compile(self.fn, dynamic=None)
        return self.compiled

    def _fail(self, exc: Exception) -> None:
        """Warn once (in one line) that compiling failed; run eagerly from now on."""
        if not self.failed:
            text = str(exc).strip()
            first = text.splitlines()[0] if text else type(exc).__name__
            # stacklevel: _fail ← __call__ ← the solver's loop ← `solve`.
            warnings.warn(f"torch.compile of the solver step failed ({first[:200]}); "
                          "running it uncompiled", RuntimeWarning, stacklevel=4)
        self.failed = True
