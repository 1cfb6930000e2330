"""The learning rate, one policy: `LRSchedule` sets every epoch's rate and the rate a run
goes on at after a rollback.

The schedules (`TrainConfig.schedule`):
- plateau, the authors' (MPNODE.jl, src/learn.jl): halve the rate after `patience` epochs
  without a better validation loss, never below `min_lr`;
- cosine: from `lr` in epoch 1 down to `min_lr` after the last epoch (SGDR's annealing,
  Loshchilov & Hutter 2017, without restarts);
- constant.

A run of bad steps rolls the weights back to the last completed epoch and goes on at half
the rate (`retry_lr`, `restart`); under cosine the rest of the curve is halved too, so that
the next epoch does not jump back up. A run whose rate would fall below `min_lr` has
diverged. The counters this policy keeps (`since_best`, `lr_scale`) live in the loop's
`LoopState`, which every checkpoint saves, so a resumed run follows the same rates.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mpnode_cli.config.train import TrainConfig
    from mpnode_cli.training.optim import Adam
    from mpnode_cli.training.run_state import MemberState


class LRSchedule:
    """The rate of `optimizer`'s every parameter group, as `config.schedule` says.

    Args:
        config: the run's config (`schedule`, `lr`, `min_lr`, `patience`, `epochs`).
        optimizer: its `param_groups[...]["lr"]` is the rate; the optimizer state that a
            checkpoint saves holds it.
        state: the counters of the model (or ensemble member) it sets the rate of;
            this policy reads and updates `since_best` and `lr_scale`.
        group: the parameter group this policy sets (an ensemble member's); None: all.
    """

    def __init__(self, config: TrainConfig, optimizer: Adam, state: MemberState,
                 group: int | None = None):
        self.config, self.optimizer, self.state, self.group = config, optimizer, state, group

    @property
    def lr(self) -> float:
        """The current rate: the one this epoch runs at."""
        return self.optimizer.param_groups[self.group or 0]["lr"]

    def start(self) -> None:
        """A new run's first epoch (a resumed run's rate is in its restored optimizer)."""
        if self.config.schedule == "cosine":
            self._set(self._cosine(1))

    def end_epoch(self, epoch: int, improved: bool) -> None:
        """Set the next epoch's rate once epoch `epoch` is validated (epoch 0, the starting
        weights validated, leaves it as it is).

        Args:
            epoch: the epoch just done.
            improved: whether its validation loss is the best so far.
        """
        config, state = self.config, self.state
        if improved:
            state.since_best = 0
        elif epoch > 0:
            state.since_best += 1
            if (config.schedule == "plateau" and state.since_best >= config.patience
                    and self.lr / 2 >= config.min_lr):
                self._set(self.lr / 2)
                state.since_best = 0
        if config.schedule == "cosine" and epoch > 0:
            self._set(self._cosine(epoch + 1) * state.lr_scale)

    def retry_lr(self) -> float | None:
        """The rate to go on at after a rollback: half the current one; None where that is
        below `min_lr` (the run has diverged)."""
        lr = self.lr / 2
        return None if lr < self.config.min_lr else lr

    def restart(self, lr: float) -> None:
        """Go on at `lr` (from `retry_lr`) once the optimizer is restored from the snapshot,
        whose state holds the snapshot's rate; the rest of a cosine curve is halved."""
        self._set(lr)
        self.state.lr_scale /= 2

    def _cosine(self, epoch: int) -> float:
        """Cosine decay from `lr` (epoch 1) to `min_lr` (after the last epoch)."""
        config = self.config
        frac = min(1.0, (epoch - 1) / max(config.epochs, 1))
        return config.min_lr + 0.5 * (config.lr - config.min_lr) * (1 + math.cos(math.pi * frac))

    def _set(self, lr: float) -> None:
        groups = self.optimizer.param_groups
        for group in groups if self.group is None else [groups[self.group]]:
            group["lr"] = lr
