"""How many CPU threads torch may use: `--threads N`, else `MPNODE_THREADS`, else one.

torch starts one OpenMP thread per core. It splits an operation across threads only above
32768 elements, and MP-NODE's operations (a 32-wide MLP over a batch of nodes) are mostly
near that size or below, so a second thread has little to share while OpenMP's spin-waits
cost CPU; when another process wants the same cores, those waits stall every operation
(docs/cli.md, "Threads", has the measurements). One thread per process is therefore
the default for every verb and every size; with idle cores and large batches, ask for more.

The choice is made here without torch (the CLI decides before it imports anything heavy);
`apply_threads` is the one place that touches torch. CUDA is left as it is: these settings
size torch's CPU thread pools only.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

ENV_VAR = "MPNODE_THREADS"
FLAG = "--threads"
DEFAULT = 1
# The most threads a process may ask for. Beyond the cores, threads only spin-wait on each
# other, and 256 is above the cores of the machines mpnode is built for; a larger count is a
# slip, and at some thousands OpenMP fails to create its pool and takes the process down.
MAX_THREADS = 256


@dataclass(frozen=True)
class ThreadChoice:
    """A thread count and where it came from: `FLAG`, `ENV_VAR` or "default"."""

    count: int
    source: str

    def describe(self) -> str:
        """`1 (default: one per process; --threads or MPNODE_THREADS to change)`."""
        if self.source == "default":
            return f"{self.count} (default: one per process; {FLAG} or {ENV_VAR} to change)"
        return f"{self.count} (from {self.source})"


_applied: ThreadChoice | None = None  # torch's pools are per process, and so is this record


def parse_count(text: str | int, where: str) -> int:
    """`text` as a thread count (1 to `MAX_THREADS`), or a `ValueError` naming `where` the
    value came from."""
    try:
        count = int(str(text).strip())
    except ValueError:
        count = 0
    if count < 1:
        raise ValueError(f"{where} must be a whole number ≥ 1, got {str(text)!r}")
    if count > MAX_THREADS:
        raise ValueError(f"{where} must be at most {MAX_THREADS}, got {str(text).strip()!r} "
                         "(one thread per process is fastest; see docs/cli.md#threads)")
    return count


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # macOS and Windows have no affinity call
        return os.cpu_count() or 1


def choose_threads(flag: str | int | None = None,
                   environ: Mapping[str, str] | None = None) -> ThreadChoice:
    """The flag if given, else the environment variable if set and not empty, else one.

    Args:
        flag: the value of `--threads`, or None when it was not given.
        environ: where to look for `MPNODE_THREADS` (default `os.environ`).

    Raises:
        ValueError: the value in use is not an integer ≥ 1 (a bad variable is ignored when
            the flag overrides it).
    """
    environ = os.environ if environ is None else environ
    if flag is not None:
        return ThreadChoice(parse_count(flag, FLAG), FLAG)
    if environ.get(ENV_VAR, "").strip():
        return ThreadChoice(parse_count(environ[ENV_VAR], ENV_VAR), ENV_VAR)
    return ThreadChoice(DEFAULT, "default")


def apply_threads(choice: ThreadChoice) -> None:
    """Size torch's intra-op pool (and its inter-op pool while it may still change)."""
    import torch

    global _applied
    torch.set_num_threads(choice.count)
    try:
        torch.set_num_interop_threads(choice.count)
    except RuntimeError:
        pass  # settable once per process, before any inter-op work; later calls keep the first
    _applied = choice


def applied_threads() -> ThreadChoice | None:
    """The last choice `apply_threads` made in this process (None before any)."""
    return _applied
