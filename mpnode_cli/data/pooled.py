"""Several datasets trained on at once (`mpnode train a.h5 b.h5 ...`).

The datasets hold one system with the same per-node state and control sizes, but their
node counts N, graphs and topologies differ — a spread of node degrees, so that a node
model learned on them transfers to larger graphs. They may also differ in the number of
samples T, on one grid: the same start time and spacing dt (a shorter set's sample times
are a prefix of a longer one's), so that a sample time means the same on all of them.

A batch tensor `[B, T, N, D]` has one N, so each batch is drawn from one dataset: every
dataset is shuffled and cut into batches as one dataset would be, and the batches of all
of them are then taken in one shuffled order (`epoch_batches`). Given a single dataset, no
draw is added: the batches are those of a one-dataset run.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.stream import StreamedTrajectories, prefetched

Data = TrajectoryData | StreamedTrajectories


def dataset_names(paths: Sequence[str | Path]) -> list[str]:
    """The name each dataset's metrics go under: its file name without `.h5`."""
    return [Path(p).stem for p in paths]


def check_poolable(datasets: Sequence[Data]) -> None:
    """Refuse, in one line, datasets that cannot be trained on together.

    Raises:
        ValueError: datasets of another system, per-node state or control size, state
            names, start time or sample spacing than the first's; the same data twice;
            two files of one name.
    """
    first, names = datasets[0], dataset_names([d.path for d in datasets])
    seen: dict[str, str] = {}
    for data, name in zip(datasets, names, strict=True):
        if data.fingerprint in seen:
            raise ValueError(f"{data.path.name} holds the same data as {seen[data.fingerprint]}:"
                             " give each dataset once")
        if name in names[:len(seen)]:
            raise ValueError(f"two datasets are named {name} ({data.path} is the second): "
                             "per-dataset metrics are kept by file name, so rename one")
        seen[data.fingerprint] = data.path.name
        for what, have, want in (
                ("system", data.system, first.system),
                ("node_dim", data.node_dim, first.node_dim),
                ("control_dim", data.control_dim, first.control_dim),
                ("state names", list(data.state_names), list(first.state_names))):
            if have != want:
                raise ValueError(
                    f"{data.path.name} has {what} {have} but {first.path.name} has {want}: "
                    "datasets trained on together must hold one system with the same "
                    "per-node sizes")
        if not _same_grid(data.time, first.time):
            raise ValueError(
                f"{data.path.name} samples from t={_t(data.time, 0)} every {_dt(data.time)} "
                f"but {first.path.name} from t={_t(first.time, 0)} every {_dt(first.time)}: "
                "datasets trained on together need the same start time and dt (their "
                "numbers of samples may differ)")


def check_ground_truth(datasets: Sequence[Data]) -> None:
    """Refuse, in one line, a file of a model's predictions (its `prediction` attribute,
    written by `evaluate --save-predictions` and `simulate`) as training data.

    Raises:
        ValueError: the first such dataset, and the option that accepts it.
    """
    for data in datasets:
        if data.attrs.get("prediction"):
            raise ValueError(
                f"{data.path.name} holds a model's predictions (mpnode evaluate "
                "--save-predictions or simulate), not ground truth: a model trained on them "
                "learns the other model's errors; pass --allow-predictions if that is meant")


def load_datasets(paths: Sequence[str | Path], stream: bool = False) -> list[Data]:
    """Read the datasets (`stream`: open the one dataset, `StreamedTrajectories`) and
    check that they can be trained on together (`check_poolable`).

    Raises:
        ValueError: `stream` with several datasets, or datasets that do not go together.
    """
    if stream and len(paths) > 1:
        raise ValueError("--stream reads one dataset from its file: train on several in "
                         "memory (leave out --stream)")
    datasets = [StreamedTrajectories.open(p) if stream else TrajectoryData.load(p)
                for p in paths]
    if len(datasets) > 1:
        check_poolable(datasets)
    return datasets


def train_and_validation(datasets: Sequence[Data], trajectories: int | None = None
                         ) -> tuple[list[Data], list[Data]]:
    """Each dataset's train split (its first `trajectories` if given) and validation split.

    Raises:
        ValueError: a dataset without train or validation trajectories.
    """
    train, validation = [], []
    for data in datasets:
        train_set, val_set = data.subset("train"), data.subset("validation")
        if trajectories is not None:
            train_set = train_set.select(torch.arange(min(trajectories, len(train_set))))
        if len(train_set) == 0 or len(val_set) == 0:
            raise ValueError(f"{data.path.name} has {len(train_set)} train and {len(val_set)} "
                             "validation trajectories: training needs both (validation "
                             "chooses the best epoch); regenerate it with more trajectories "
                             "or a --split that gives each some")
        train.append(train_set)
        validation.append(val_set)
    return train, validation


def fewer_than_asked(datasets: Sequence[Data], train: Sequence[Data],
                     trajectories: int | None) -> str | None:
    """One line when `trajectories` (K) exceeds a dataset's train split, which is then used
    whole (`train` is `train_and_validation`'s); None when every split has K. A data-size
    study would otherwise compare runs of one size unawares."""
    short = [f"{data.path.name} has {len(part)}"
             for data, part in zip(datasets, train, strict=True)
             if trajectories is not None and len(part) < trajectories]
    if not short:
        return None
    return (f"--trajectories {trajectories}: {', '.join(short)} train trajectories; training "
            "on all of them")


def _same_grid(a: torch.Tensor, b: torch.Tensor) -> bool:
    """Whether the shorter of two sample grids is the start of the longer (to rounding)."""
    n = min(a.numel(), b.numel())
    scale = max(1.0, float(a.abs().max()), float(b.abs().max()))
    return bool(torch.allclose(a[:n].double(), b[:n].double(), rtol=0, atol=1e-9 * scale))


def _t(time: torch.Tensor, k: int) -> str:
    return f"{float(time[k]):g}"


def _dt(time: torch.Tensor) -> str:
    return f"{float(time[1] - time[0]):g}" if time.numel() > 1 else "(one sample)"


def epoch_batches(sizes: Sequence[int], batch_size: int, even: bool,
                  generator: torch.Generator) -> list[tuple[int, torch.Tensor]]:
    """One epoch's batches over datasets of `sizes` trajectories each.

    Each dataset is shuffled (`randperm`, in the order given) and cut into batches, then
    (with several datasets) the batches are put in a random order.

    Args:
        sizes: K_i, trajectories of each dataset's train split.
        batch_size: B, trajectories per batch, per dataset.
        even: ⌈K_i/B⌉ batches whose sizes differ by at most one; else full batches and a
            partial last one (the authors' DataLoader).
        generator: the loop's generator (its state is saved with every checkpoint).

    Returns:
        `(dataset index, trajectory indices [B_b] int64)` per batch, in training order.
    """
    batches = []
    for i, k in enumerate(sizes):
        order = torch.randperm(k, generator=generator)
        if even:
            parts = order.tensor_split(max(1, -(-k // batch_size)))
        else:
            parts = order.split(batch_size)
        batches += [(i, idx) for idx in parts if len(idx)]
    if len(sizes) == 1:  # one dataset: the batches of a one-dataset run, no draw added
        return batches
    return [batches[j] for j in torch.randperm(len(batches), generator=generator).tolist()]


@contextmanager
def taken(datasets: Sequence[Data], plan: Sequence[tuple[int, torch.Tensor]]
          ) -> Iterator[Iterator[TrajectoryData]]:
    """The batches `datasets[i].take(index)` for each `(i, index)` of `plan`, in order.

    One dataset may be streamed (`prefetched` reads ahead in a thread); several are in
    memory, where a batch is taken when it is asked for.
    """
    if len(datasets) == 1:
        with prefetched(datasets[0], [index for _, index in plan]) as batches:
            yield batches
        return
    yield (datasets[i].take(index) for i, index in plan)


def element_weights(datasets: Sequence[Any]) -> list[int]:
    """Predicted values per dataset, K · (T − 1) · N · D: the weights of pooled MSEs."""
    return [len(d) * (d.time.numel() - 1) * d.num_nodes * d.node_dim for d in datasets]
