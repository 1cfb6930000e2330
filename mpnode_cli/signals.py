"""SIGINT and SIGTERM handled alike: both interrupt a run, and a file being written either
appears whole or not at all.

A batch scheduler stops a job with SIGTERM where a person presses Ctrl-C (SIGINT). Python
turns only SIGINT into `KeyboardInterrupt`; under `interrupt_on_signals` SIGTERM raises the
same exception (an `Interrupted`, which says which signal), so every `except
KeyboardInterrupt` that cleans up serves both.

Libraries that write files from C (h5py, torch.save) can swallow an exception raised in
the middle of their work ("Exception ignored in ...") and then finish the file as if
nothing happened. `deferred_signals` keeps such a write out of the way of signals: it
records them, lets the writer ask at safe points (`Deferred.check`), and raises once the
block ends.
"""

from __future__ import annotations

import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Interrupted(KeyboardInterrupt):
    """A `KeyboardInterrupt` raised for a signal; `signum` says which (exit 128 + signum)."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def exit_code(exc: BaseException) -> int:
    """The shell's exit status for an interrupt: 130 for SIGINT (Ctrl-C), 143 for SIGTERM."""
    return 128 + (exc.signum if isinstance(exc, Interrupted) else signal.SIGINT)


def signal_name(exc: BaseException) -> str:
    """"SIGTERM" or "SIGINT" (a plain `KeyboardInterrupt` is Ctrl-C)."""
    return signal.Signals(exc.signum).name if isinstance(exc, Interrupted) else "SIGINT"


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


_received: int | None = None  # the signal `interrupt_on_signals` raised for, if any


def _raise(signum: int, frame) -> None:
    global _received
    _received = _received or signum
    raise Interrupted(signum)


def raise_if_interrupted() -> None:
    """Raise `Interrupted` again if a signal has been raised for in this block.

    The handler raises wherever Python code happens to run, and a library that catches
    every exception (a compiler tracing a function, for one) can swallow it and go on; a
    loop that calls this at safe points (after each batch) stops all the same.
    """
    if _received is not None:
        raise Interrupted(_received)


def _quiet_unraisable(previous):
    """A `sys.unraisablehook` that drops our own `Interrupted`: raised in a callback whose
    exceptions Python only prints (a weakref callback of torch's compiler, a `__del__`),
    it would print a traceback on stderr, although `raise_if_interrupted` raises it again
    at the next safe point. Every other unraisable exception goes to `previous`."""

    def hook(unraisable) -> None:
        if not isinstance(unraisable.exc_value, Interrupted):
            previous(unraisable)

    return hook


@contextmanager
def interrupt_on_signals() -> Iterator[None]:
    """Within the block, SIGINT and SIGTERM both raise `Interrupted`.

    Outside the main thread (where Python cannot set handlers) the block runs unchanged.
    """
    global _received
    if not _in_main_thread():
        yield
        return
    old = {signum: signal.signal(signum, _raise) for signum in _SIGNALS}
    outer, _received = _received, None
    old_hook, sys.unraisablehook = sys.unraisablehook, _quiet_unraisable(sys.unraisablehook)
    try:
        yield
    finally:
        for signum, handler in old.items():
            signal.signal(signum, handler)
        sys.unraisablehook = old_hook
        _received = outer


class Deferred:
    """Signals that arrived while deferred; `check()` raises for the first of them."""

    def __init__(self) -> None:
        self.received: int | None = None

    def record(self, signum: int, frame) -> None:
        self.received = self.received or signum

    def check(self) -> None:
        """Raise `Interrupted` if a signal arrived (call between steps of a write)."""
        if self.received is not None:
            raise Interrupted(self.received)


_deferring: Deferred | None = None  # the outermost `deferred_signals` block's, if any


@contextmanager
def deferred_signals() -> Iterator[Deferred]:
    """Within the block, SIGINT and SIGTERM are recorded instead of raised.

    The block may call `check()` at points where stopping is safe; a signal that arrived
    and was not raised there is raised when the block ends without another exception.
    A block inside another defers to the outer one: its `check()` never raises, and the
    signal is raised when the outermost block ends.
    """
    global _deferring
    pending = Deferred()
    if not _in_main_thread() or _deferring is not None:
        # Nested: the outer block records the signal and raises it when *it* ends, so
        # that a group of writes (a checkpoint and its metrics row) is all done or none.
        yield pending
        return
    old = {signum: signal.signal(signum, pending.record) for signum in _SIGNALS}
    _deferring = pending
    try:
        yield pending
    finally:
        _deferring = None
        for signum, handler in old.items():
            signal.signal(signum, handler)
    pending.check()
