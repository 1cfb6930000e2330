"""Stopping a run cleanly, after an epoch, when its training step is outgrowing memory.

The start-of-run estimate (`mpnode_cli.training.step_memory`) measures the untrained
model's step. A step's memory is what autograd keeps at each right-hand-side evaluation,
so it grows as training goes on: with the horizon curriculum (longer rollouts) and as the
learned field stiffens (more solver steps). On a CPU the operating system's out-of-memory
killer then ends the process with exit 137, mid-epoch, with no line saying why.

`EpochPeaks` measures each epoch's peak resident memory (Linux's `VmHWM`, reset at the
start of the epoch through `/proc/self/clear_refs`) and, after the epoch is saved, stops
the run when two more epochs of the recent growth would not fit in what the process can
still reach: its resident memory now plus what the OS calls available
(`mpnode_cli.memory.available_memory`). A run whose peak does not grow is never stopped,
however close to the limit it runs: it already fits. The rule looks two epochs ahead
because one epoch's rise is noisy (batches differ in how many solver steps they take) and
a run killed mid-epoch loses that epoch; a run stopped one epoch early loses nothing, as
`last.pt` holds it and `--resume` continues on a machine with more memory.

A `--memory-budget` lowers what the process can reach to the budget. A run of a neural ODE
that backpropagates through every solver step is not stopped but switched, for the epochs
that follow, to checkpointed backprop (`CHECKPOINTS` stored states: the same gradient, in
memory that does not grow with the steps); one already checkpointing is stopped.

On CUDA an allocation that fails raises an exception that `mpnode_cli.memory.naming_memory`
names, so no guard is needed there, and none runs. Where `/proc/self/clear_refs` cannot be
written (not Linux), the guard is off.
"""

from __future__ import annotations

import itertools
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from mpnode_cli.memory import OutOfMemory, available_memory, format_bytes, parse_size
from mpnode_cli.models.ode import NeuralODEModel
from mpnode_cli.terminal import suggested
from mpnode_cli.training import run as runs

if TYPE_CHECKING:
    from mpnode_cli.training.run_state import Run

# How many epoch-to-epoch rises the projection looks back over, and ahead.
LOOKBACK = 3
AHEAD = 2
# Solver states a checkpointed step keeps (`SolverOptions.checkpoints`): with 64 a step runs
# 3 times up to ~2000 solver steps, 4 up to ~70 000 (docs/solver.md).
CHECKPOINTS = 64

_STATUS = "/proc/self/status"
_CLEAR_REFS = "/proc/self/clear_refs"


def _status_bytes(field: str) -> int | None:
    """A `kB` field of `/proc/self/status` (`VmHWM`, `VmRSS`) in bytes; None if unreadable."""
    try:
        with open(_STATUS, encoding="ascii") as f:
            text = f.read()
    except OSError:
        return None
    match = re.search(rf"^{field}:\s+(\d+)\s+kB", text, re.MULTILINE)
    return int(match.group(1)) * 1024 if match else None


def reset_peak() -> bool:
    """Reset this process's peak resident memory to what it holds now; False where the OS
    has no such reset (it is Linux's "5" to `/proc/self/clear_refs`)."""
    try:
        with open(_CLEAR_REFS, "w", encoding="ascii") as f:
            f.write("5")
    except OSError:
        return False
    return True


def peak_bytes() -> int | None:
    """This process's peak resident memory since the last `reset_peak` (or its start)."""
    return _status_bytes("VmHWM")


def resident_bytes() -> int | None:
    """This process's resident memory now."""
    return _status_bytes("VmRSS")


def projected_overrun(peaks: Sequence[int], resident: int, available: int) -> int | None:
    """The peak the run is projected to reach, if it will not fit; None if it will.

    `peaks` are the epochs' peak resident bytes, oldest first; `resident` what the process
    holds now and `available` what it may still take, so it can reach `resident +
    available`. The projection is the last peak plus `AHEAD` times the largest rise over
    the last `LOOKBACK` epochs; a run whose peaks did not rise is never projected over.
    """
    if len(peaks) < 2:
        return None
    recent = list(peaks[-(LOOKBACK + 1):])
    rise = max(b - a for a, b in itertools.pairwise(recent))
    if rise <= 0:
        return None
    projected = peaks[-1] + AHEAD * rise
    return projected if projected > resident + available else None


class EpochPeaks:
    """Each epoch's peak resident memory, and whether the next epochs will still fit."""

    def __init__(self, device_type: str, budget: str | None = None):
        self.on = device_type == "cpu" and os.path.exists(_CLEAR_REFS)
        self.peaks: list[int] = []
        self.budget = None if budget is None else parse_size(budget)

    def begin(self) -> None:
        """Call as an epoch starts."""
        if self.on:
            self.on = reset_peak()

    def end(self) -> str | None:
        """Call once the epoch is saved: None to go on, or why the run should stop."""
        if not self.on or (peak := peak_bytes()) is None:
            return None
        self.peaks.append(peak)
        resident, available = resident_bytes(), available_memory()
        if resident is None or available is None:
            return None
        reach, limit = resident + available, "this process can reach"
        if self.budget is not None and self.budget < reach:
            reach, limit = self.budget, "--memory-budget allows"
        projected = projected_overrun(self.peaks, resident, reach - resident)
        if projected is None:
            return None
        first = self.peaks[-(LOOKBACK + 1):][0]
        return (f"the training step's peak memory grew from {format_bytes(first)} to "
                f"{format_bytes(peak)} over the last epochs, and two more epochs at that "
                f"rate would need about {format_bytes(projected)}, more than the "
                f"{format_bytes(reach)} {limit}")


# What a process whose own step fits says when another's does not.
OTHER_RANK = "another training process's step is outgrowing its memory"


def stop_if_outgrowing(run: Run, epoch: int, peaks: EpochPeaks) -> None:
    """After a saved epoch (`epoch`; `run` the loop's `Run`), when any process's step is
    outgrowing its memory (`peaks.end()`): switch a neural ODE's plain backprop to
    checkpointed backprop for the next epochs (`run.config` and config.json say so, and a
    warning line), or stop the run, with an interrupted `summary.json` and one line.

    Raises:
        OutOfMemory: the line, with how to continue.
    """
    why = peaks.end()
    stop = run.world.max(torch.tensor([float(why is not None)], dtype=torch.float64))
    if not stop[0]:
        return
    solver = run.config.solver
    if solver.checkpoints is None and isinstance(run.members[0], NeuralODEModel):
        run.config = run.config.model_copy(update={
            "solver": solver.model_copy(update={"checkpoints": CHECKPOINTS})})
        if run.world.main:
            runs.write_json(Path(run.run_dir) / runs.CONFIG, run.config.model_dump(mode="json"))
        run.emit({"event": "warning", "text": f"after epoch {epoch}, {why or OTHER_RANK}: "
                  f"the next epochs backpropagate through checkpointed solves ({CHECKPOINTS} "
                  "stored states; the same gradient, about 1.5–2× the time)"})
        peaks.peaks.clear()  # plain backprop's peaks say nothing of checkpointed epochs'
        return
    if run.world.main:
        runs.write_interrupted(run.run_dir, epoch, "memory")
    even = " even with checkpointed backprop" if solver.checkpoints is not None else ""
    raise OutOfMemory(
        f"training stopped after epoch {epoch} of {run.config.epochs}: "
        f"{why or OTHER_RANK}{even}. "
        f"last.pt keeps epoch {epoch} and best.pt the best so far; continue on a machine "
        f"with more memory (or a larger --memory-budget) with: "
        f"{suggested('train', '--resume', Path(run.run_dir))}, "
        f"or train again with a lower --batch-size")
