"""Resuming a run: what may change, and what must stay as it was.

A resumed run is the run its folder describes: its `config.json` (the resolved config, every
field explicit, so no recipe applies again) and its `last.pt` (weights, optimizer, RNG
states and the loop's counters), so that 2 + 2 epochs train as 4 did. Only what leaves the
losses as they are may change (`RESUMABLE`): the total of epochs, the time limit, the
device, the plots, and streaming (which reads the same batches). Its datasets are found
from any folder (their paths are absolute), and datasets given again are accepted when they
hold the same data, in the same order (`check_same_data`: by fingerprint).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from mpnode_cli.config import TrainConfig
from mpnode_cli.terminal import suggested
from mpnode_cli.training.run import read_config

if TYPE_CHECKING:
    from mpnode_cli.training.checkpoint import Checkpoint

# The rest would make the run something else (streaming reads the same batches).
RESUMABLE = ("epochs", "time_limit", "device", "plots", "stream")


def resumable_options() -> str:
    """`--epochs, --device, --plots and --stream`: the options `RESUMABLE` stands for."""
    flags = ["--" + name.replace("_", "-") for name in RESUMABLE]
    return ", ".join(flags[:-1]) + " and " + flags[-1]


def resume_config(run_dir: Path, datasets: list[Path] | None,
                  changes: dict[str, Any]) -> TrainConfig:
    """The config that continues the run in `run_dir`.

    Args:
        run_dir: the run folder.
        datasets: its datasets again (e.g. moved), in the run's order; None: the paths in
            its config.
        changes: config fields given anew (the CLI's options); only `RESUMABLE` ones.

    Raises:
        ValueError: not a run folder, a field that may not change, datasets that do not
            match the run's in number, or missing ones (one line that says what to give).
    """
    config = read_config(run_dir)
    changed = sorted(set(changes) - set(RESUMABLE))
    if changed:
        shown = ", ".join("--" + name.replace("_", "-") for name in changed)
        raise ValueError(f"--resume continues {run_dir} as configured; only "
                         f"{resumable_options()} may change (got {shown})")
    trained = config.datasets
    if datasets is not None and len(datasets) != len(trained):
        raise ValueError(f"{run_dir} trained on {_count(len(trained), 'dataset')} but "
                         f"{_count(len(datasets), 'was', 'were')} given: give all of them, in "
                         "the run's order, or none")
    gone = [str(p) for p in trained if not Path(p).is_file()]
    if datasets is None and gone:
        how, word = (("its new path", "DATASET") if len(trained) == 1 else
                     ("the paths of all its datasets, in order", "DATASET..."))
        raise ValueError(f"{run_dir} trained on {', '.join(gone)}, which is not there any "
                         f"more: give {how}, {suggested('train', word, '--resume', run_dir)}")
    # Datasets given are taken if they are the same data: training compares fingerprints.
    where = {"dataset": [d.resolve() for d in datasets]} if datasets is not None else {}
    return TrainConfig(**{**config.model_dump(), **changes, **where, "run_dir": run_dir})


def check_resumable(config: TrainConfig, last: Checkpoint, datas: list,
                    finished_ok: bool) -> None:
    """Refuse to resume from `last` (the run's `last.pt`) on other data than the run's, or
    with no epochs left to train unless `finished_ok`.

    Raises:
        ValueError: one line that says what to give instead.
    """
    check_same_data(last, datas)
    if config.epochs <= last.epoch and not finished_ok:
        raise ValueError(f"{config.run_dir} has trained {last.epoch} epochs already; --epochs "
                         f"is the total, so give more than {last.epoch} to continue it")


def check_same_data(last: Checkpoint, datas: list) -> None:
    """Refuse to resume a run on other data than it trained on (by fingerprint, in order)."""
    records = last.dataset.get("datasets") or [last.dataset]
    if [r["fingerprint"] for r in records] == [d.fingerprint for d in datas]:
        return
    if len(records) == 1 and len(datas) == 1:
        raise ValueError(f"{datas[0].path} is not the dataset this run trained on (its "
                         "fingerprint differs from the run's): resume needs the same data")
    given = ", ".join(str(d.path) for d in datas)
    raise ValueError(f"{given} are not the {len(records)} datasets this run trained on, in "
                     "its order (their fingerprints differ from the run's): resume needs the "
                     "same data")


def _count(n: int, one: str, several: str | None = None) -> str:
    """`1 dataset`, `2 datasets`; `1 was`, `2 were`."""
    return f"{n} {one if n == 1 else several or one + 's'}"
