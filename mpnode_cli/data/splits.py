"""How a dataset's trajectories are split into train, validation and test: by trajectory,
shuffled with a generator of its own (`mpnode generate` and `mpnode import` alike)."""

from __future__ import annotations

import numpy as np


def split_trajectories(k: int, fractions: tuple[float, float, float], seed: int) -> np.ndarray:
    """uint8 `[K]`: 0 train, 1 validation, 2 test, shuffled by trajectory.

    Its own generator (`default_rng([seed, 1])`), so the split does not depend on how many
    initial states were redrawn.
    """
    n_train, n_val, _ = split_counts(k, fractions)
    split = np.full(k, 2, dtype=np.uint8)
    order = np.random.default_rng([seed, 1]).permutation(k)
    split[order[:n_train]] = 0
    split[order[n_train : n_train + n_val]] = 1
    return split


def split_counts(k: int, fractions: tuple[float, float, float]) -> tuple[int, int, int]:
    """Trajectories in train, validation and test of a K-trajectory split: train and
    validation rounded, test what is left."""
    n_train = round(k * fractions[0])
    n_val = min(round(k * fractions[1]), k - n_train)
    return n_train, n_val, k - n_train - n_val


# What a dataset without trajectories in a split cannot do.
_EMPTY_SPLIT = {"train": "nothing to train on",
                "validation": "mpnode train refuses such a dataset (validation chooses the best "
                              "epoch)",
                "test": "no test error after training, and evaluate's default split is empty"}


def split_warning(counts: tuple[int, int, int],
                  fractions: tuple[float, float, float]) -> str | None:
    """One line for a split that leaves train, validation or test without trajectories (a
    small K, or a fraction of 0), saying what that costs; None when none is empty."""
    from mpnode_cli.data.hdf5 import SPLIT_NAMES

    empty = [name for name, n in zip(SPLIT_NAMES, counts, strict=True) if n == 0]
    if not empty:
        return None
    shown = ",".join(f"{x:g}" for x in fractions)
    costs = "; ".join(f"{name}: {_EMPTY_SPLIT[name]}" for name in empty)
    return (f"{sum(counts)} trajectories split {shown} leave "
            f"{' and '.join(f'0 {name}' for name in empty)} trajectories ({costs}): use more "
            "trajectories or another --split")
