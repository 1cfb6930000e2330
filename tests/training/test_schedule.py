"""`LRSchedule`: the learning-rate policy of training, against its closed forms."""

from __future__ import annotations

import math

import torch

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.training.lr_schedule import LRSchedule
from mpnode_cli.training.optim import Adam
from mpnode_cli.training.run_state import MemberState


def schedule(**fields) -> LRSchedule:
    config = TrainConfig(dataset="d.h5", **fields)
    optimizer = Adam([torch.nn.Parameter(torch.zeros(2))], lr=config.lr)
    return LRSchedule(config, optimizer, MemberState())


def test_plateau_halves_after_patience_and_stops_at_min_lr():
    s = schedule(schedule="plateau", lr=1.0, min_lr=0.2, patience=2)
    s.end_epoch(0, improved=True)
    rates = []
    for epoch in range(1, 9):
        s.end_epoch(epoch, improved=epoch == 2)  # a gain starts the count again
        rates.append(s.lr)  # the next epoch's
    assert rates == [1.0, 1.0, 1.0, 0.5, 0.5, 0.25, 0.25, 0.25]  # 0.125 < min_lr


def test_cosine_runs_from_lr_to_min_lr_and_a_restart_halves_the_rest():
    s = schedule(schedule="cosine", lr=1e-2, min_lr=1e-4, epochs=4)
    s.start()
    want = [1e-4 + 0.5 * (1e-2 - 1e-4) * (1 + math.cos(math.pi * (e - 1) / 4))
            for e in range(1, 6)]
    assert s.lr == want[0]
    s.end_epoch(1, improved=True)
    assert s.lr == want[1]
    lr = s.retry_lr()
    assert lr == want[1] / 2
    s.restart(lr)
    assert s.lr == lr and s.state.lr_scale == 0.5
    s.end_epoch(2, improved=False)
    assert s.lr == want[2] * 0.5


def test_no_retry_below_min_lr():
    s = schedule(schedule="constant", lr=1e-3, min_lr=6e-4)
    assert s.retry_lr() is None
    s.end_epoch(1, improved=False)
    assert s.lr == 1e-3  # constant
