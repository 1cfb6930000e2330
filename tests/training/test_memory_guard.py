"""The per-epoch memory guard: a training whose step outgrows memory stops cleanly after a
saved epoch, with one line, instead of being killed mid-epoch (exit 137)."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import torch

from mpnode_cli.training import memory_guard
from mpnode_cli.training.memory_guard import AHEAD, projected_overrun
from tests.conftest import invoke, one_line_error

GIB = 2**30


def test_projection_is_the_last_peak_plus_two_of_the_largest_recent_rises():
    peaks = [10 * GIB, 11 * GIB, 11.5 * GIB, 12 * GIB]
    # largest rise over the last three: 1 GiB, so two epochs ahead is 14 GiB
    assert projected_overrun(peaks, resident=4 * GIB, available=9 * GIB) == 14 * GIB
    assert projected_overrun(peaks, resident=4 * GIB, available=10 * GIB) is None
    # the rise of 9 GiB (1 → 10) is older than the three looked back over: still 12 + 2 × 1
    assert projected_overrun([1 * GIB, 10 * GIB, *peaks[1:]], 4 * GIB, 9 * GIB) == 14 * GIB


@pytest.mark.parametrize("peaks", [[20 * GIB, 20 * GIB, 19 * GIB], [5 * GIB]])
def test_a_run_whose_peak_does_not_grow_is_never_stopped(peaks):
    """Stable (or a single epoch's) peak: it fits already, however near the limit."""
    assert projected_overrun(peaks, resident=1 * GIB, available=0) is None


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="Linux's VmHWM")
def test_the_peak_is_measured_and_reset():
    """An allocation of 256 MiB shows in the peak, and the reset forgets it once freed."""
    if not memory_guard.reset_peak():
        pytest.skip("/proc/self/clear_refs is not writable here")
    before = memory_guard.peak_bytes()
    block = np.ones(256 * 2**20 // 8)  # written, so resident
    during = memory_guard.peak_bytes()
    del block
    assert during - before >= 250 * 2**20
    assert memory_guard.reset_peak()
    assert memory_guard.peak_bytes() <= during - 250 * 2**20


def test_training_stops_after_a_saved_epoch_and_resumes(tmp_path, gene_2x2, monkeypatch):
    """Peaks that rise 1 GiB an epoch against 1.5 GiB of headroom: after epoch 2 (the
    first with a rise) the run switches to checkpointed backprop, and as they still rise
    it stops after epoch 4, exit 2 and one line; epoch 4 is saved, the summary says why,
    and `--resume` finishes the run once memory allows."""
    pytest.importorskip("resource")
    peaks = iter(range(GIB, 100 * GIB, GIB))
    monkeypatch.setattr(memory_guard.EpochPeaks, "__init__", _always_on)
    monkeypatch.setattr(memory_guard, "reset_peak", lambda: True)
    monkeypatch.setattr(memory_guard, "peak_bytes", lambda: next(peaks))
    monkeypatch.setattr(memory_guard, "resident_bytes", lambda: GIB)
    monkeypatch.setattr(memory_guard, "available_memory", lambda: GIB + GIB // 2)
    run = tmp_path / "run"
    result = invoke("train", gene_2x2, "--epochs", 6, "--batch-size", 17, "--no-plots",
                    "--run-dir", run)
    line = one_line_error(result)
    assert "after epoch 2, " in result.output and "checkpointed solves" in result.output
    assert "training stopped after epoch 4 of 6" in line and "even with checkpointed" in line
    assert f"need about {AHEAD + 4} GiB" in line and "--resume" in line
    summary = json.loads((run / "summary.json").read_text())
    assert summary["interrupted"] == "memory" and summary["finished"] is False
    last = torch.load(run / "checkpoints" / "last.pt", weights_only=False)
    assert last["epoch"] == 4 and last["train_config"]["solver"]["checkpoints"] == 64
    monkeypatch.undo()
    result = invoke("train", "--resume", run, "--no-plots")
    assert result.exit_code == 0, result.output
    assert json.loads((run / "summary.json").read_text())["epochs"] == 6


def _always_on(self, device_type: str, budget: str | None = None) -> None:
    self.on, self.peaks, self.budget = True, [], None
