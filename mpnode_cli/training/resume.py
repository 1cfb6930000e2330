"""Resuming a run: what may change, and what must stay as it was.

A resumed run is the run its folder describes: its `config.json` (the resolved config, every
field explicit, so no recipe applies again) and its `last.pt` (weights, optimizer, RNG
states and the loop's counters), so that 2 + 2 epochs train as 4 did. Only what leaves the
losses as they are may change (`RESUMABLE`): the total of epochs, the time limit, the
device, the plots, streaming (which reads the same batches) and the memory budget (the
checkpointed backprop it may start gives the same gradient). Its datasets are found from
any folder (their paths are absolute), and datasets given again are accepted when they
hold the same data, in the same order (`check_same_data`: by fingerprint). A config file
given again is taken when it asks for what the run is (`file_changes`).

A run that trained all its epochs but was stopped before it wrote its summary (killed
while it tested its best checkpoint) finishes when resumed with the same `--epochs`.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.terminal import suggested
from mpnode_cli.textfiles import read_json
from mpnode_cli.training.run import SUMMARY, read_config

if TYPE_CHECKING:
    from mpnode_cli.training.checkpoint import Checkpoint

# The rest would make the run something else (streaming reads the same batches).
RESUMABLE = ("epochs", "time_limit", "device", "plots", "stream", "memory_budget")


def resumable_options() -> str:
    """`--epochs, --device, ... and --memory-budget`: the options `RESUMABLE` stands for."""
    flags = ["--" + name.replace("_", "-") for name in RESUMABLE]
    return ", ".join(flags[:-1]) + " and " + flags[-1]


def resume_config(run_dir: Path, datasets: list[Path] | None, changes: dict[str, Any],
                  config_file: Path | None = None) -> TrainConfig:
    """The config that continues the run in `run_dir`.

    Args:
        run_dir: the run folder.
        datasets: its datasets again (e.g. moved), in the run's order; None: the paths in
            its config.
        changes: config fields given anew (the CLI's options); only `RESUMABLE` ones.
        config_file: a config file given again (`file_changes`); `changes` override it.

    Raises:
        ValueError: not a run folder, a field that may not change, datasets that do not
            match the run's in number, or missing ones (one line that says what to give).
    """
    config = read_config(run_dir)
    if config_file is not None:
        changes = file_changes(config, config_file, run_dir) | changes
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


def file_changes(config: TrainConfig, config_file: Path, run_dir: Path) -> dict[str, Any]:
    """The `RESUMABLE` fields of a config file given to resume the run of `config`.

    Its other fields must be the run's (a `[model_options]` or `[solver]` table: the keys
    it gives; paths: the same file; a solver `compile = "auto"`: whatever the run settled).

    Raises:
        ValueError: a file that does not read or validate, or one that would change the
            run (one line naming its fields that differ).
    """
    from mpnode_cli.config.file import read_config_file
    from mpnode_cli.config.upgrade import upgrade_train_fields

    fields = upgrade_train_fields(read_config_file(config_file))
    ours = config.model_dump()
    merged = {k: ({**ours[k], **v} if isinstance(ours.get(k), dict) and isinstance(v, dict)
                  else v) for k, v in fields.items()}
    if merged.get("solver", {}).get("compile") == "auto":
        merged["solver"]["compile"] = ours["solver"]["compile"]
    theirs = TrainConfig(**{**ours, **merged}).model_dump()
    differ = [k for k in fields if k not in RESUMABLE and not _same(k, theirs[k], ours[k],
                                                                  run_dir)]
    if differ:
        raise ValueError(f"--resume continues {run_dir} as configured; only "
                         f"{resumable_options()} may change (got --config {config_file} "
                         f"with other {', '.join(differ)})")
    return {k: theirs[k] for k in fields if k in RESUMABLE}


def _same(key: str, theirs: Any, ours: Any, run_dir: Path) -> bool:
    """Whether a config file's field is the run's (paths: the same file)."""
    if key == "run_dir":
        return theirs is None or Path(theirs).resolve() == Path(run_dir).resolve()
    if key in ("dataset", "init_checkpoint") and theirs is not None and ours is not None:
        return _resolved(theirs) == _resolved(ours)
    return theirs == ours


def _resolved(paths: Any) -> list[Path]:
    return [Path(p).resolve() for p in (paths if isinstance(paths, list) else [paths])]


def check_resumable(config: TrainConfig, last: Checkpoint, datas: list,
                    finished_ok: bool) -> None:
    """Refuse to resume from `last` (the run's `last.pt`) on other data than the run's, or
    with no epochs left to train unless `finished_ok` or the run is yet to write the
    summary of those epochs (it was stopped as it tested them: this finishes it).

    Raises:
        ValueError: one line that says what to give instead.
    """
    check_same_data(last, datas)
    finished_ok = finished_ok or (config.epochs == last.epoch
                                  and not _summarized(config.run_dir, last.epoch))
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


def _summarized(run_dir: Path | None, epochs: int) -> bool:
    """Whether the run's summary.json is that of a run finished after `epochs` epochs."""
    path = Path(run_dir or ".") / SUMMARY
    try:
        summary = read_json(path) if path.is_file() else None
    except ValueError:
        return False
    return isinstance(summary, dict) and summary.get("finished") is True and (
        summary.get("epochs") == epochs)


def _count(n: int, one: str, several: str | None = None) -> str:
    """`1 dataset`, `2 datasets`; `1 was`, `2 were`."""
    return f"{n} {one if n == 1 else several or one + 's'}"
