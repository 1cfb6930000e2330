"""What a training run works with (`Run`) and the loop's counters a checkpoint saves
(`LoopState`, one `MemberState` per ensemble member), as `mpnode_cli.training.setup` makes
them and the epochs update them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories
from mpnode_cli.training import distributed
from mpnode_cli.training.optim import Adam

OnEvent = Callable[[dict[str, Any]], None]


@dataclass
class MemberState:
    """One model's own counters (an ensemble has one per member).

    Attributes:
        best_epoch, best_val: its best validation loss so far, and the epoch of it.
        since_best: epochs without gain since the best or the last lr halving (plateau).
        bad_run: skipped batches in a row. lr_scale: cosine's scale after rollbacks.
        stopped: the epoch after which early stopping froze it (0: still training).
    """

    best_epoch: int = 0
    best_val: float = math.inf
    since_best: int = 0
    bad_run: int = 0
    lr_scale: float = 1.0
    stopped: int = 0


# MemberState's fields that a one-model checkpoint of an earlier mpnode keeps at the top of
# its `loop`.
_OWN = ("best_epoch", "best_val", "since_best", "bad_run", "lr_scale")


@dataclass
class LoopState:
    """The loop's counters, saved in every checkpoint so that a resume continues exactly.

    `epoch`, `skipped`, `restores` and `seconds` are the run's; the rest is each member's
    (`members`, one for a single model: an ensemble of one).
    """

    epoch: int = 0
    skipped: int = 0
    restores: int = 0
    seconds: float = 0.0
    members: list[MemberState] = field(default_factory=lambda: [MemberState()])

    def to_dict(self) -> dict[str, Any]:
        """The checkpoint's `loop`: the run's counters, and each member's under `members`."""
        return {"epoch": self.epoch, "skipped": self.skipped, "restores": self.restores,
                "seconds": self.seconds, "members": [asdict(m) for m in self.members]}

    @staticmethod
    def from_dict(loop: dict[str, Any]) -> LoopState:
        shared = {k: loop[k] for k in ("epoch", "skipped", "restores", "seconds") if k in loop}
        # An earlier mpnode kept a single model's counters at the top.
        members = loop.get("members") or [{k: loop[k] for k in _OWN if k in loop}]
        return LoopState(**shared, members=[MemberState(**m) for m in members])


@dataclass
class Run:
    """What a training run works with, from `set_up`.

    Attributes:
        config: resolved: the recipe applied, absolute dataset paths, the model that was
            built and its options, `run_dir` set (what `config.json` holds).
        run_dir: the run folder.
        world: the processes (one without torchrun); rank 0 alone writes and reports.
        emit: the progress callback (it ignores every event on the other ranks).
        datas: every dataset, in order (`TrajectoryData`, or `StreamedTrajectories`).
        names: their names in metrics and summary (`mpnode_cli.data.pooled.dataset_names`).
        train_sets: each dataset's train split (its first `trajectories`).
        val_parts: this rank's part of each dataset's validation split.
        facts: what a checkpoint records of the datasets and their training range.
        kind, model_config: the model's registry name and its full config.
        model, normalizer, optimizer: on `device`.
        shuffle: the loop's generator: batch order and noise, the same on any device.
        shuffles: each member's generator (`shuffle` is the first: a single model's).
        state: the loop's counters.
        resumed: whether the run continues from its `last.pt`.
        parent_sha: the SHA-256 of the checkpoint a finetune started from (None for a
            run trained from scratch).
    """

    config: TrainConfig
    run_dir: Path
    world: distributed.World
    emit: OnEvent
    datas: list[TrajectoryData | StreamedTrajectories]
    names: list[str]
    train_sets: list[TrajectoryData | StreamedTrajectories]
    val_parts: list[TrajectoryData | StreamedTrajectories]
    facts: dict[str, Any]
    kind: str
    model_config: dict[str, Any]
    model: torch.nn.Module
    normalizer: Normalizer
    optimizer: Adam
    shuffle: torch.Generator
    device: torch.device
    state: LoopState
    resumed: bool
    parent_sha: str | None
    shuffles: list[torch.Generator]
    # Each training dataset's factor on its loss (`--balance-datasets`); None: 1 for each.
    loss_scale: list[float] | None = None

    @property
    def members(self) -> list[torch.nn.Module]:
        """The models trained: an ensemble's members, or the one model (its one member)."""
        return list(self.model.members)

    def active(self) -> list[int]:
        """The members still training (not frozen by early stopping)."""
        return [k for k, m in enumerate(self.state.members) if not m.stopped]
