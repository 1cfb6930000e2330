"""Calling a system's own code: its errors named after the method, and its vector field
checked as the solver calls it.

These are the pieces of the plug-in contract (`mpnode_cli.systems.contract`) that
`System` itself uses (its default `simulate` solves a checked `rhs`), kept apart so that
`systems/base.py` and the contract do not import each other.
"""

from __future__ import annotations

import contextlib
import inspect
import os
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from mpnode_cli.memory import is_out_of_memory

if TYPE_CHECKING:
    from mpnode_cli.systems.base import RHS, System


class PluginError(ValueError):
    """A system's method broke its contract or raised: one line naming where."""


class HardExit(SystemExit):
    """`os._exit(code)` called by a plug-in's code (`no_hard_exit`)."""

    def __str__(self) -> str:
        return f"it called os._exit({self.code}), which would end mpnode without a word"


@contextlib.contextmanager
def no_hard_exit() -> Iterator[None]:
    """While a plug-in's code runs (its file imported, a method called), `os._exit` raises
    `HardExit` instead of ending the process at once (which would skip every message,
    leave an output file empty and exit 0); a plug-in has no reason to end mpnode. An exit
    from C code cannot be caught this way."""
    real = os._exit

    def refuse(code: int = 0) -> None:
        raise HardExit(code)

    os._exit = refuse
    try:
        yield
    finally:
        os._exit = real


def where(system: Any, method: str) -> str:
    """`FitzHughNagumo.rhs (examples/fitzhugh_nagumo.py)`: a method of a system's class,
    and the file that defines it."""
    cls = system if inspect.isclass(system) else type(system)
    try:
        source = inspect.getfile(cls)
    except (TypeError, OSError):
        source = cls.__module__
    return f"{cls.__name__}.{method} ({source})"


def named(system: Any, method: str, exc: BaseException) -> BaseException:
    """The exception to raise for `exc`, raised inside `system.method`: a `PluginError`
    naming where, or `exc` itself (a `KeyboardInterrupt`, a `PluginError` already, a
    `ValueError` that mpnode's own code raised, or memory running out, which is the job's
    size and not the method's fault: the caller names the step, `mpnode_cli.memory`)."""
    if isinstance(exc, KeyboardInterrupt | PluginError) or is_out_of_memory(exc):
        return exc
    if isinstance(exc, ValueError):
        if not _through_plugin(system, exc):
            return exc
        return PluginError(f"{where(system, method)}: {exc}")
    if isinstance(exc, HardExit):
        return PluginError(f"{where(system, method)}: {exc}")
    if isinstance(exc, SystemExit):
        return PluginError(f"{where(system, method)} called sys.exit({exc.code!r})")
    return PluginError(f"{where(system, method)} raised {type(exc).__name__}: {exc}")


def _through_plugin(system: Any, exc: BaseException) -> bool:
    """Whether `exc` was raised in, or passed through, a plug-in's own code."""
    cls = system if inspect.isclass(system) else type(system)
    if cls.__module__.startswith("mpnode_cli."):
        return False
    try:
        source = inspect.getfile(cls)
    except (TypeError, OSError):
        return True
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_filename == source:
            return True
        tb = tb.tb_next
    return False


def call(system: Any, method: str, *args: Any, **kwargs: Any) -> Any:
    """`system.method(*args, **kwargs)`, whose errors are `named` after it."""
    try:
        with no_hard_exit():
            return getattr(system, method)(*args, **kwargs)
    except BaseException as exc:  # a plug-in's sys.exit is an error too
        raise named(system, method, exc) from None


def checked_rhs(system: System, f: Any) -> RHS:
    """`f`, a system's vector field, with each result checked: a torch tensor of the shape,
    dtype and device of `y`, finite at the first call (the initial states).

    Raises:
        PluginError: `f` is not callable (at once), or a result breaks the contract, or `f`
            raises (when called).
    """
    import torch

    here = where(system, "rhs")
    if not callable(f):
        raise PluginError(f"{here} returned {described(f)}, not a function f(t, y)")
    first = True

    def checked(t: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        nonlocal first
        try:
            with no_hard_exit():
                dy = f(t, y)
        except BaseException as exc:
            raise named(system, "rhs", exc) from None
        if not (isinstance(dy, torch.Tensor) and dy.shape == y.shape and dy.dtype == y.dtype
                and dy.device == y.device):
            raise PluginError(f"{here}: f(t, y) returned {described(dy)} for y "
                              f"{described(y)}; it must return dy/dt, a tensor like y")
        if first:  # one check, at the initial states: a sync per call would cost every step
            first = False
            bad = ~torch.isfinite(dy).flatten(1).all(1)
            if bad.any():
                raise PluginError(f"{here}: f(t, y) is NaN or inf at the initial states of "
                                  f"{int(bad.sum())} of {len(bad)} trajectories (the first: "
                                  f"{int(bad.nonzero()[0, 0])})")
        return dy

    return checked


def described(value: Any) -> str:
    """A value as an error message shows it: an array's shape and dtype, else its type."""
    shape, dtype = getattr(value, "shape", None), getattr(value, "dtype", None)
    if shape is not None and dtype is not None:
        device = getattr(value, "device", None)
        on = f" on {device}" if device is not None and str(device) != "cpu" else ""
        return f"shape {list(shape)} {dtype}{on}"
    return f"a value of type {type(value).__name__}"
