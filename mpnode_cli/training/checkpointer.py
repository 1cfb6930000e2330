"""`Checkpointer`: what a training run leaves in its folder after each epoch, and on an
interrupt.

Each epoch's files are its metrics row, `last.pt` and, if its validation loss is the best
so far, `best.pt`, written in that order: `last.pt` (which holds the row too) commits the
epoch, so that a process killed between two of the writes leaves a folder that a resume
brings back to `last.pt` (`mpnode_cli.training.run_folder`). A signal waits for all three
(`mpnode_cli.signals.deferred_signals`), so that `last.pt`'s epoch is then the last row of
metrics.jsonl. The snapshot, a copy of
the last completed epoch's checkpoint, is what `last.pt` holds, what a run of bad steps
rolls back to, and what Ctrl-C or SIGTERM leaves behind.
"""

from __future__ import annotations

import copy
from typing import Any

import torch

from mpnode_cli.signals import deferred_signals, signal_name
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from mpnode_cli.training.run_state import Run


class Checkpointer:
    """The epochs' files of `run` (rank 0 writes them) and the snapshot of the last
    completed epoch, taken when made (the starting point)."""

    def __init__(self, run: Run):
        self.run = run
        self.snapshot = self._copy()
        # best.pt holds each member's best weights, which may be of different epochs (an
        # ensemble's): they are kept here (a resumed run's from its best.pt).
        best = runs.checkpoint_path(run.run_dir, "best")
        self.best_weights: dict[str, torch.Tensor] = (
            load_checkpoint(best).state_dict if run.resumed and best.exists()
            else copy.deepcopy(run.model.state_dict()))

    def checkpoint(self, metrics: dict[str, Any] | None = None) -> Checkpoint:
        """The run as it is now (its tensors shared with the model and optimizer)."""
        run = self.run
        rng = {"torch": torch.get_rng_state(), "shuffle": run.shuffle.get_state(),
               "member_shuffles": torch.stack([g.get_state() for g in run.shuffles])}
        return Checkpoint(
            model_kind=run.kind, model_config=run.model_config,
            state_dict=run.model.state_dict(), normalizer=run.normalizer.to_dict(),
            train_config=run.config.model_dump(mode="json"), dataset=run.facts,
            epoch=run.state.epoch, optimizer=run.optimizer.state_dict(), rng=rng,
            loop=run.state.to_dict(), parent_sha256=run.parent_sha, metrics=metrics or {},
        )  # fmt: skip

    def save_epoch(self, row: dict[str, Any]) -> None:
        """Take the snapshot of the epoch just done (with its metrics `row`), and write its
        files: the row, then `last.pt`, then `best.pt` if a member improved (its best
        epoch is this one; each member that did has its weights replace its own there).

        Signals are held for the whole of it, the snapshot included, so an interrupt comes
        after all three writes or before any; the interrupt handler (`save_interrupted`)
        then saves the snapshot it has.
        """
        run = self.run
        improved = [k for k, m in enumerate(run.state.members) if m.best_epoch == run.state.epoch]
        with deferred_signals():
            self.snapshot = self._copy()
            self.snapshot.metrics = copy.deepcopy(row)
            if not run.world.main:
                return
            runs.append_metrics(run.run_dir, row)
            save_checkpoint(runs.checkpoint_path(run.run_dir, "last"), self.snapshot)
            if improved:
                save_checkpoint(runs.checkpoint_path(run.run_dir, "best"),
                                self._best(row, improved))

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

    def _best(self, row: dict[str, Any], improved: list[int]) -> Checkpoint:
        """The checkpoint `best.pt` takes: the run as it is now, with each member's best
        weights (the `improved` members' current ones)."""
        ckpt = self.checkpoint(row)
        for k in improved:
            prefix = self.run.model.member_prefix(k)
            for name, value in ckpt.state_dict.items():
                if name.startswith(prefix):
                    self.best_weights[name] = value.detach().clone()
        ckpt.state_dict = dict(self.best_weights)
        return ckpt

    def _copy(self) -> Checkpoint:
        """A deep copy: the optimizer and model update their tensors in place."""
        return copy.deepcopy(self.checkpoint())
