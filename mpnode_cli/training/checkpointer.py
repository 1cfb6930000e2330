"""`Checkpointer`: what a training run leaves in its folder after each epoch, and on an
interrupt.

Each epoch's files are its metrics row, `last.pt` and, if its validation loss is the best
so far, `best.pt`. They are written all or none (`mpnode_cli.signals.deferred_signals`),
so that `last.pt`'s epoch is always the last row of metrics.jsonl. The snapshot, a copy of
the last completed epoch's checkpoint, is what `last.pt` holds, what a run of bad steps
rolls back to, and what Ctrl-C or SIGTERM leaves behind.
"""

from __future__ import annotations

import copy
from dataclasses import asdict
from typing import Any

import torch

from mpnode_cli.signals import deferred_signals, signal_name
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint, save_checkpoint
from mpnode_cli.training.setup import Run


class Checkpointer:
    """The epochs' files of `run` (rank 0 writes them) and the snapshot of the last
    completed epoch, taken when made (the starting point)."""

    def __init__(self, run: Run):
        self.run = run
        self.snapshot = self._copy()

    def checkpoint(self, metrics: dict[str, Any] | None = None) -> Checkpoint:
        """The run as it is now (its tensors shared with the model and optimizer)."""
        run = self.run
        return Checkpoint(
            model_kind=run.kind, model_config=run.model_config,
            state_dict=run.model.state_dict(), normalizer=run.normalizer.to_dict(),
            train_config=run.config.model_dump(mode="json"), dataset=run.facts,
            epoch=run.state.epoch, optimizer=run.optimizer.state_dict(),
            rng={"torch": torch.get_rng_state(), "shuffle": run.shuffle.get_state()},
            loop=asdict(run.state), parent_sha256=run.parent_sha, metrics=metrics or {},
        )  # fmt: skip

    def save_epoch(self, row: dict[str, Any], *, best: bool) -> None:
        """Take the snapshot of the epoch just done, and write its files: `best.pt` if it
        improved (`best`), its metrics `row`, then `last.pt`.

        Signals are held for the whole of it, the snapshot included, so an interrupt comes
        after all three writes or before any; the interrupt handler (`save_interrupted`)
        then saves the snapshot it has.
        """
        run = self.run
        with deferred_signals():
            self.snapshot = self._copy()
            if not run.world.main:
                return
            if best:
                save_checkpoint(runs.checkpoint_path(run.run_dir, "best"), self.checkpoint(row))
            runs.append_metrics(run.run_dir, row)
            save_checkpoint(runs.checkpoint_path(run.run_dir, "last"), self.snapshot)

    def save_interrupted(self, exc: KeyboardInterrupt) -> None:
        """Save the snapshot as `last.pt` and an interrupted `summary.json` (rank 0), for
        the interrupt `exc`."""
        if not self.run.world.main:
            return
        try:
            with deferred_signals():  # a second signal must not cut the save short
                save_checkpoint(runs.checkpoint_path(self.run.run_dir, "last"), self.snapshot)
                runs.write_interrupted(self.run.run_dir, self.snapshot.epoch, signal_name(exc))
        except KeyboardInterrupt:
            pass  # it came during the save, which finished: stop, as both signals asked

    def _copy(self) -> Checkpoint:
        """A deep copy: the optimizer and model update their tensors in place."""
        return copy.deepcopy(self.checkpoint())
