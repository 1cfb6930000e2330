"""Memory as a user meets it: sizes in words, what this process may still take, and running
out of it named after the step that did.

The memory a job will take is estimated before it runs (`mpnode_cli.data.size`) and
compared with `available_memory`. When an estimate falls short anyway, the allocation
fails as a `MemoryError` (numpy, Python), or as torch's `RuntimeError` ("DefaultCPUAllocator:
can't allocate memory") or `torch.OutOfMemoryError` (CUDA); `naming_memory` turns any of
them into one `OutOfMemory` line that names the step ("out of memory while solving
trajectories 3–4 of 8"), never the code that happened to ask for the bytes.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated

from pydantic import AfterValidator

# What torch's CPU and CUDA allocators say when they fail (they raise RuntimeError).
_ALLOCATOR_WORDS = ("can't allocate memory", "out of memory")


class OutOfMemory(ValueError):
    """A step ran out of memory: one line naming the step and what to change (exit 2)."""


def format_bytes(n: float) -> str:
    """`1.5 GiB`, `320 MiB`, `12 KiB`: a size for a person."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} PiB"  # unreachable: the loop returns at TiB


def parse_size(text: str) -> int:
    """Bytes of `4GiB`, `1.5 GiB`, `500MiB`, `4G` (powers of 1024), `4GB` (of 1000) or a
    number of bytes.

    Raises:
        ValueError: anything else, or not above zero (one line, with examples).
    """
    match = re.fullmatch(r"\s*(\d+(?:\.\d*)?)\s*(?:([kKMGT])(iB|B)?)?\s*", text)
    size = 0
    if match:
        number, unit, suffix = match.groups()
        power = " KMGT".index(unit.upper()) if unit else 0
        size = int(float(number) * (1000 if suffix == "B" else 1024) ** power)
    if size < 1:
        raise ValueError(f"'{text}' is not a memory size: give e.g. 4GiB, 1.5GiB or 500MiB")
    return size


def _memory_size(text: str) -> str:
    parse_size(text)
    return text.strip()


# A config's memory size: kept as written (`4GiB`), checked as `parse_size` reads it.
MemorySize = Annotated[str, AfterValidator(_memory_size)]


def format_seconds(seconds: float) -> str:
    """`40 s`, `12 min`, `3.5 h`, `2.1 days`: a duration for a person."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.2g} h"
    return f"{seconds / 86400:.2g} days"


def available_memory() -> int | None:
    """The bytes this process may still allocate: the least of the memory the OS calls
    available (Linux's `MemAvailable`, else the machine's physical memory) and what is left
    of an address-space limit (`ulimit -v`); None where the OS says neither."""
    limits = [m for m in (_meminfo_available() or _physical(), _address_space_left())
              if m is not None]
    return min(limits) if limits else None


def _physical() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return None


def _meminfo_available() -> int | None:
    """Linux's estimate of the memory new work can take without swapping (in bytes)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def _address_space_left() -> int | None:
    """The address-space limit (`RLIMIT_AS`) less what the process maps already."""
    try:
        import resource

        soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    except (ImportError, ValueError, OSError):
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/statm", encoding="ascii") as f:
            mapped = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        mapped = 0
    return max(soft - mapped, 0)


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether `exc` is an allocation that failed: a `MemoryError`, or torch's allocator
    refusing (a `RuntimeError` whose message says so, `torch.OutOfMemoryError` among them)."""
    if isinstance(exc, MemoryError):
        return True
    return isinstance(exc, RuntimeError) and any(w in str(exc) for w in _ALLOCATOR_WORDS)


@contextmanager
def naming_memory(step: object, need: int | None = None, advice: str = "") -> Iterator[None]:
    """Within the block, running out of memory is one `OutOfMemory` line naming `step`.

    Args:
        step: what the block does, as the line names it ("solving trajectories 3–4 of 8"):
            a string, or an object whose `str` says the step it is at when memory runs out.
        need: the job's estimated peak memory in bytes, if known.
        advice: what to change ("lower --chunk-size").

    Raises:
        OutOfMemory: an allocation in the block failed (`is_out_of_memory`).
    """
    try:
        yield
    except OutOfMemory:
        raise
    except BaseException as exc:
        if not is_out_of_memory(exc):
            raise
        raise OutOfMemory(memory_message(str(step), need, advice)) from None


def memory_message(step: str, need: int | None, advice: str = "") -> str:
    """`out of memory while STEP (about N GiB needed, M GiB available): ADVICE`."""
    have = available_memory()
    sizes = []
    if need is not None:
        sizes.append(f"about {format_bytes(need)} needed")
    if have is not None:
        sizes.append(f"{format_bytes(have)} available now")
    text = f"out of memory while {step}"
    if sizes:
        text += f" ({', '.join(sizes)})"
    return f"{text}: {advice}" if advice else text
