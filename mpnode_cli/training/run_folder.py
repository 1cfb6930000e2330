"""A run folder as one training holds it: locked for the training's life, checked whole
before a resumed run writes anything, and brought back to its `last.pt` after a crash.

Each epoch is committed in one order (`mpnode_cli.training.checkpointer.Checkpointer`):
its metrics row is appended to metrics.jsonl, then `last.pt` is replaced (the commit; it
holds the row too), then, if the epoch improved, `best.pt`. Each checkpoint and record is
replaced by a rename (`mpnode_cli.data.atomic`), so a process killed at any point (SIGKILL
too) leaves one of these states, which a resume brings back to `last.pt`'s epoch
(`recover`, under the lock and after the checks):

- killed during an epoch, or during a recovery: the last epoch's files, as they were;
- after the row and before `last.pt`: the row is beyond `last.pt`'s epoch and is dropped
  (as is a row the kill cut short, which has no line end);
- after `last.pt` and before `best.pt`: `best.pt` is behind the best epoch `last.pt`
  records; it is written again from `last.pt` (an ensemble's: the members that improved
  from `last.pt`, the others from the `best.pt` there);
- during a write: its temporary file is left behind, and removed.

The resumed run then trains the lost epochs again, as they were (2 + 2 epochs train as 4
do). A `best.pt` ahead of `last.pt` (earlier versions of mpnode wrote `best.pt` first) is
kept: that epoch is trained again and writes it again.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Any

import torch

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.config.upgrade import pin_stored_solver, upgrade_train_fields
from mpnode_cli.models.registry import build_model
from mpnode_cli.textfiles import read_text
from mpnode_cli.training import run as runs
from mpnode_cli.training.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from mpnode_cli.training.resume import RESUMABLE
from mpnode_cli.training.runlock import RunLock, lock_run

# What a checkpoint's train config may hold otherwise than config.json: what a resume
# may change, and where the run and its data are now.
_MAY_DIFFER = (*RESUMABLE, "run_dir", "dataset")

# `mpnode_cli.path_limits.temp_beside`'s names: `.<name>.<pid>.<random>.tmp`.
_TEMPORARY = re.compile(r"^\..+\.(\d+)\.[0-9a-f]{8}\.tmp$")


class RunFolder:
    """The run folder of one training (rank 0's), from `train`'s start to its end.

    A resumed run's is locked and checked by `resume` before anything is read into the
    run; `open` makes and locks a new run's (or recovers a resumed run's) and writes its
    config; leaving the `with` block removes a new run's folder that failed before its
    first checkpoint, then releases the lock.

    Attributes:
        last: a resumed run's `last.pt`, checked (None for a new run and on other ranks).
    """

    def __init__(self):
        self.path: Path | None = None
        self.last: Checkpoint | None = None
        self._best: Checkpoint | None = None
        self._existed: bool | None = None  # a new run's folder: whether it was there, empty
        self._lock: RunLock | None = None

    def __enter__(self) -> RunFolder:
        return self

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        try:
            # A new run that failed before its first last.pt: a husk, neither resumable
            # nor reusable.
            if kind is not None and self._existed is not None:
                runs.remove_unstarted(self.path, keep_folder=self._existed)
        finally:
            if self._lock is not None:
                self._lock.release()

    def resume(self, config: TrainConfig) -> None:
        """Lock the run folder `config.run_dir` and check it whole (`check_run_folder`);
        nothing is written.

        Raises:
            ValueError: another process holds it, or what `check_run_folder` refuses.
        """
        if config.run_dir is None:
            raise ValueError("resume needs the run folder (run_dir)")
        run_dir = Path(config.run_dir)
        runs.read_config(run_dir)  # "not a run folder" before any lock
        self._lock = lock_run(run_dir)
        self.path = run_dir
        self.last, self._best = check_run_folder(run_dir, config)

    def reserve(self, run_dir: Path) -> None:
        """Make and lock a new run's folder before the run is set up, for what the run
        makes there first (`--for-graphs`' coverage data); `open` then takes it as it is.

        Raises:
            ValueError: as `mpnode_cli.training.run.create` and `lock_run`.
        """
        existed = not runs.create(run_dir)
        self.path, self._existed = run_dir, existed
        self._lock = lock_run(run_dir)

    def open(self, run_dir: Path, config: TrainConfig) -> None:
        """Make and lock a new run's folder (unless `reserve` did), or bring a resumed run's
        back to its `last.pt` (`recover`); then write the config.

        Raises:
            ValueError: as `mpnode_cli.training.run.create` and `lock_run`.
        """
        if self.last is not None:
            recover(run_dir, self.last, self._best)
        elif self.path != run_dir:
            existed = not runs.create(run_dir)
            self.path, self._existed = run_dir, existed
            self._lock = lock_run(run_dir)
        runs.write_json(run_dir / runs.CONFIG, config.model_dump(mode="json"))


def check_run_folder(run_dir: Path, config: TrainConfig
                     ) -> tuple[Checkpoint, Checkpoint | None]:
    """Check all that a resume of `run_dir` reads and writes, before it writes anything.

    Its config.json must validate; its `last.pt` and `best.pt` must be valid checkpoints
    of this run (the train config of config.json, but for what a resume may change and
    where the data are) holding the weights of the model that config builds (names and
    shapes); metrics.jsonl must reach `last.pt`'s epoch; `best.pt` must hold the best epoch
    `last.pt` records, or be one that `recover` rewrites; and the folder, `checkpoints/`,
    `plots/` (if `config.plots`) and the files there must be writable.

    Returns:
        `last.pt` and `best.pt` (None if there is none).

    Raises:
        ValueError: the first problem, in one line; a file or folder this process may not
            read (`checkpoints/` without the permission to enter it) too.
    """
    try:
        return _check_run_folder(run_dir, config)
    except OSError as exc:
        if exc.filename is None:
            raise
        raise ValueError(f"cannot resume {run_dir}: cannot read {exc.filename}: "
                         f"{exc.strerror or exc} (nothing was changed)") from None


def _check_run_folder(run_dir: Path, config: TrainConfig
                      ) -> tuple[Checkpoint, Checkpoint | None]:
    stored = runs.read_config(run_dir)
    if not runs.checkpoint_path(run_dir, "last").is_file():
        raise ValueError(f"{run_dir} has no checkpoints/last.pt to resume from (it stopped "
                         "before its first epoch was saved): delete it, or train again "
                         "with another --run-dir")
    last = load_checkpoint(runs.checkpoint_path(run_dir, "last"))
    best_path = runs.checkpoint_path(run_dir, "best")
    best = load_checkpoint(best_path) if best_path.exists() else None
    model = _model_of(stored, last, run_dir)
    for ckpt in (last, best):
        if ckpt is not None:
            _check_own(ckpt, stored, model, run_dir)
    _check_metrics(run_dir, last)
    _check_best(last, best)
    _check_writable(run_dir, config)
    return last, best


def recover(run_dir: Path, last: Checkpoint, best: Checkpoint | None) -> None:
    """Bring a checked run folder back to its `last.pt` (the cases in the module's
    docstring): remove dead writers' temporaries, drop metrics rows beyond its epoch, and
    write `best.pt` again where it is behind. Each step is atomic and may be done again."""
    _remove_temporaries(run_dir)
    rows = _metrics(run_dir, last.epoch)
    runs.truncate_metrics(run_dir, last.epoch, rows)
    epochs = _best_epochs(last.loop)
    if max(epochs) == last.epoch and (best is None or best.epoch < last.epoch):
        row = last.metrics or next(r for r in rows if r["epoch"] == last.epoch)
        with torch.device("meta"):  # where each member's weights are, without memory
            model = build_model(last.model_kind, last.model_config)
        # best.pt's weights, but for the members that improved at last.pt's epoch.
        state = dict((last if best is None else best).state_dict)
        for k in (k for k, epoch in enumerate(epochs) if epoch == last.epoch):
            state |= {n: v for n, v in last.state_dict.items()
                      if n.startswith(model.member_prefix(k))}
        save_checkpoint(runs.checkpoint_path(run_dir, "best"),
                        dataclasses.replace(last, metrics=row, state_dict=state))


def _model_of(stored: TrainConfig, last: Checkpoint, run_dir: Path) -> torch.nn.Module:
    """The model config.json builds (on the meta device: shapes without memory), at the
    data sizes `last` records (and its options where an earlier config.json left them
    out)."""
    try:
        recorded = {k: v for k, v in last.model_config.items() if k != "members"}
        with torch.device("meta"):
            return build_model(stored.model, recorded | stored.model_options
                               | {"members": stored.seeds})
    except (TypeError, ValueError, RuntimeError) as exc:
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        # The model config.json names cannot take last.pt's options: most likely a
        # checkpoint of another model put there, which is what the line names.
        raise ValueError(f"{run_dir}/checkpoints/last.pt is not a checkpoint of the model "
                         f"its {runs.CONFIG} builds ({first}): put the run's own last.pt "
                         "back, or train again with another --run-dir") from None


def _check_own(ckpt: Checkpoint, stored: TrainConfig, model: torch.nn.Module,
               run_dir: Path) -> None:
    """Refuse a checkpoint of another run, or one whose weights do not fit the model."""
    theirs, ours = _settled(ckpt.train_config), stored.model_dump(mode="json")
    # A model option added since the checkpoint was written is its default there: the
    # model that older mpnode built (a checkpoint of an earlier session's resume).
    for config in (theirs, ours):
        config["model_options"] = _with_defaults(config["model"], config["model_options"])
        # A run may start checkpointed backprop as its step outgrows memory (same gradient).
        config["solver"] = {k: v for k, v in config["solver"].items() if k != "checkpoints"}
    differ = [k for k in ours if k not in _MAY_DIFFER and theirs.get(k) != ours[k]]
    if differ:
        raise ValueError(f"{ckpt.path} is not this run's checkpoint: it and "
                         f"{run_dir}/{runs.CONFIG} differ in {', '.join(differ)} (a "
                         f"checkpoint of another run, or an edited {runs.CONFIG})")
    want, have = model.state_dict(), ckpt.state_dict
    missing, extra = [n for n in want if n not in have], [n for n in have if n not in want]
    wrong = [n for n in want if n in have and tuple(have[n].shape) != tuple(want[n].shape)]
    for what, names in (("lacks weights the model has", missing),
                        ("has weights the model does not", extra),
                        ("has weights of other shapes than the model's", wrong)):
        if names:
            raise ValueError(f"{ckpt.path} does not fit the model {run_dir}/{runs.CONFIG} "
                             f"builds: it {what}: {', '.join(names[:3])}"
                             + (" ..." if len(names) > 3 else ""))


def _with_defaults(model: str, options: dict[str, Any]) -> dict[str, Any]:
    """`options` with every option the model declares (its defaults where left out), or
    as they are for a model this mpnode does not know (`_check_own` then refuses it)."""
    from mpnode_cli.models.registry import resolve_options

    try:
        return resolve_options(model, options).model_dump(mode="json")
    except ValueError:
        return options


def _settled(train_config: dict[str, Any]) -> dict[str, Any]:
    """A stored train config as config.json would hold it (upgraded, validated)."""
    return TrainConfig(**pin_stored_solver(upgrade_train_fields(dict(train_config)))
                       ).model_dump(mode="json")


def _metrics(run_dir: Path, last_epoch: int) -> list[dict[str, Any]]:
    """metrics.jsonl's rows, less a last one that a kill cut short as it was appended: no
    line end, not JSON, after rows that reach `last_epoch` (it was the next epoch's).

    Raises:
        ValueError: any other line that is not a row.
    """
    path = run_dir / runs.METRICS
    try:
        return runs.read_metrics(run_dir)
    except ValueError:
        text = read_text(path, "")
        head = text[:text.rfind("\n") + 1]
        rows = runs.metrics_rows(head, path) if head != text else None
        if not rows or rows[-1]["epoch"] < last_epoch:
            raise
        return rows


def _check_metrics(run_dir: Path, last: Checkpoint) -> None:
    """metrics.jsonl must hold `last.pt`'s epoch (rows beyond it are a crash's, dropped)."""
    kept = [r["epoch"] for r in _metrics(run_dir, last.epoch) if r["epoch"] <= last.epoch]
    if not kept or kept[-1] != last.epoch:
        have = f"ends at epoch {kept[-1]}" if kept else "has no rows"
        raise ValueError(f"{run_dir}/{runs.METRICS} {have}, but checkpoints/last.pt is of "
                         f"epoch {last.epoch}: a damaged run folder")


def _check_best(last: Checkpoint, best: Checkpoint | None) -> None:
    """`best.pt` must hold the best epoch `last.pt` records, be behind it where that is
    `last.pt`'s own epoch (a kill between the two writes, which `recover` mends), or be
    ahead of `last.pt` (an earlier mpnode's order of writes)."""
    epochs = _best_epochs(last.loop)
    top = max(epochs)
    if best is None:
        if min(epochs) != last.epoch:  # else every member's best is last.pt's weights
            raise ValueError(f"{last.path.parent} has no best.pt beside last.pt: a damaged "
                             "run folder")
        return
    if best.epoch != top and best.epoch <= last.epoch and not best.epoch < top == last.epoch:
        raise ValueError(f"{best.path} is of epoch {best.epoch}, but checkpoints/last.pt "
                         f"records epoch {top} as the best: a damaged run folder")


def _best_epochs(loop: dict[str, Any]) -> list[int]:
    """Each member's best epoch, from a checkpoint's `loop` (one for a single model)."""
    members = loop.get("members") or [loop]
    return [int(m.get("best_epoch", 0)) for m in members]


def _check_writable(run_dir: Path, config: TrainConfig) -> None:
    """Refuse a run folder that the resumed run could not write to the end."""
    from mpnode_cli.path_limits import check_writable_dir

    folders = [run_dir, run_dir / "checkpoints"]
    if config.plots and (run_dir / "plots").is_dir():
        folders.append(run_dir / "plots")
    for folder in folders:
        check_writable_dir(folder)
    for path in (run_dir / runs.CONFIG, run_dir / runs.METRICS, run_dir / runs.SUMMARY,
                 runs.checkpoint_path(run_dir, "last"), runs.checkpoint_path(run_dir, "best")):
        if path.exists() and not os.access(path, os.W_OK):
            raise ValueError(f"cannot write {path}: it is read-only (the resumed run "
                             "replaces it)")


def _remove_temporaries(run_dir: Path) -> None:
    """Remove the temporaries of writers that were killed (their process is gone)."""
    for folder in (run_dir, run_dir / "checkpoints", run_dir / "plots"):
        for path in folder.glob(".*.tmp") if folder.is_dir() else ():
            match = _TEMPORARY.match(path.name)
            if match and not _alive(int(match.group(1))):
                path.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's: alive
        return True
    return True
