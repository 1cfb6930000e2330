"""The run folder `runs/<name>/`: where a training run leaves everything it made.

    config.json         the resolved `TrainConfig` (rebuilds the run: `TrainConfig(**json)`;
                        the dataset's path (or datasets' paths) absolute, so the run
                        resumes from anywhere)
    metrics.jsonl       one JSON object per epoch (epoch 0 = the starting weights, validated)
    summary.json        written at the end: best epoch, minimum validation loss, test metrics,
                        the paper's Table-2 figure, wall time, parameter count, processes
                        (and, from the CLI, the CPU threads torch used by each); a run
                        stopped by Ctrl-C or SIGTERM writes one with `finished: false` and
                        `interrupted` (the signal; "memory" where the memory guard
                        stopped it, `mpnode_cli.training.memory_guard`)
    checkpoints/        best.pt (lowest validation loss) and last.pt (latest epoch)
    (no file)           the folder itself is locked while a training writes it
                        (`mpnode_cli.training.runlock`); a resume checks it whole first
                        and mends what a killed run left (`mpnode_cli.training.run_folder`)
    plots/              test-split plots of the best checkpoint
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.config.upgrade import pin_stored_solver, upgrade_train_fields
from mpnode_cli.data.atomic import atomic_text
from mpnode_cli.jsonable import jsonable
from mpnode_cli.terminal import suggested
from mpnode_cli.textfiles import read_json, read_text

CONFIG, METRICS, SUMMARY = "config.json", "metrics.jsonl", "summary.json"


@dataclass
class TrainSummary:
    """What `summary.json` holds: `train`'s result.

    `table2` is the paper's Table-2 figure, best epoch × minimum validation loss; `test`
    holds `EvalResult.to_dict()` of the best checkpoint on the test split (None without one)
    and `baselines` the naive predictors' MSE on that split, `{hold_x0, time_mean}` (see
    `mpnode_cli.training.evaluate.baseline_mse`). `world_size` is the number of processes
    that trained (torchrun's data parallelism; 1 without it).

    `stopped_early` is the last epoch of a run that early stopping (`stop_patience`) ended
    before its `epochs`, else None.

    An ensemble (`seeds` S > 1): `test` is the members' mean prediction's, with each
    member's under `test["members"]` and their mean ± std (`members_mean`, `members_std`,
    `mpnode_cli.training.evaluate.member_stats`); `members` lists each member's seed, best
    epoch, best validation loss, early stop and test result; `best_epoch` is the latest of
    the members' and `min_val_loss` their mean. None for a single model.

    A run on several datasets: `dataset`, `dataset_fingerprint` and `num_nodes` are the
    first dataset's; `min_val_loss`, `min_val_mse`, `test` and `baselines` are pooled (means
    over every value of every dataset's split, so each dataset weighs by its number of
    predicted values, K · (T − 1) · N · D); `by_dataset` holds each dataset's own by name
    (its file name without `.h5`): path, fingerprint, num_nodes, val_mse (at the best
    epoch), test and baselines. It is None for one dataset.
    """

    run_dir: str
    model: str
    model_config: dict[str, Any]
    parameters: int
    dataset: str
    dataset_fingerprint: str
    system: str
    num_nodes: int
    loss: str
    epochs: int
    best_epoch: int
    min_val_loss: float
    min_val_mse: float | None
    table2: float
    test: dict[str, Any] | None
    wall_seconds: float
    seconds_per_epoch: float | None
    skipped_batches: int
    restores: int
    init_checkpoint: str | None
    parent_sha256: str | None
    baselines: dict[str, Any] | None = None
    finished: bool = True
    world_size: int = 1
    by_dataset: dict[str, Any] | None = None
    stopped_early: int | None = None
    members: list[dict[str, Any]] | None = None


def default_root() -> Path:
    """Where run folders go unless `--run-dir` says otherwise."""
    return Path("runs")


def default_run_dir(dataset: Path | list[Path], model: str, root: Path | None = None) -> Path:
    """`runs/<dataset stem>-<model>-<YYYYmmdd-HHMMSS>`, with a suffix if that exists;
    several datasets: `<first stem>+<how many more>`."""
    from mpnode_cli.path_limits import NAME_MAX, shorten

    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    paths = dataset if isinstance(dataset, list) else [dataset]
    tail = (f"+{len(paths) - 1}" if len(paths) > 1 else "") + f"-{model}-{stamp}"
    # A dataset's name may use all of a name's bytes: shorten it, leaving room for `-<n>`.
    stem = shorten(Path(paths[0]).stem, NAME_MAX - 8 - len(tail))
    base = (root or default_root()) / f"{stem}{tail}"
    path, n = base, 1
    while path.exists():
        n += 1
        path = base.with_name(f"{base.name}-{n}")
    return path


def check_new(run_dir: Path) -> None:
    """Refuse a new run's folder that holds a run already or cannot be made: checked before
    any work (loading, building, measuring), and again by `create`.

    Raises:
        ValueError: one line.
    """
    from mpnode_cli.paths import check_output_folder

    check_output_folder(run_dir)
    if run_dir.is_dir() and any(run_dir.iterdir()):
        if not (run_dir / CONFIG).is_file():  # a folder of other files: nothing to resume
            raise ValueError(f"{run_dir} is a folder of other files, not a run folder: "
                             "choose a new or empty --run-dir")
        raise ValueError(f"run folder {run_dir} already exists: continue it with "
                         f"{suggested('train', '--resume', run_dir)}, or choose another --run-dir")


def create(run_dir: Path) -> bool:
    """Make a new run folder; refuse to train over an existing run (`check_new`), or beside
    another training that took the same folder (`mpnode_cli.paths.reserve_folder`).

    Returns:
        Whether the folder itself was made (an existing empty folder is used as it is).

    Raises:
        ValueError: the folder holds a run already, or cannot be made (one line).
    """
    from mpnode_cli.paths import reserve_folder

    check_new(run_dir)
    try:
        return reserve_folder(run_dir, "checkpoints")
    except FileExistsError:  # since the line above
        raise ValueError(f"run folder {run_dir} was just taken by another training: choose "
                         "another --run-dir") from None


def remove_unstarted(run_dir: Path, *, keep_folder: bool = False) -> None:
    """Empty a new run folder that has no `last.pt` yet (a run that failed before its
    first checkpoint), so that its name can be used again, and remove it unless
    `keep_folder` (it existed, empty, before the run). A folder with `last.pt` is kept: it
    can be resumed."""
    if checkpoint_path(run_dir, "last").exists():
        return
    if not keep_folder:
        shutil.rmtree(run_dir, ignore_errors=True)
        return
    for child in Path(run_dir).iterdir():
        if child.is_dir() and not child.is_symlink():
            shutil.rmtree(child, ignore_errors=True)
        else:
            child.unlink(missing_ok=True)


def write_interrupted(run_dir: Path, epoch: int, signal: str) -> None:
    """`summary.json` of a run stopped by a signal: what its metrics say so far, and how to
    continue it."""
    path = Path(run_dir) / SUMMARY
    path.unlink(missing_ok=True)  # read_summary would return a previous (finished) one
    truncate_metrics(run_dir, epoch)  # a row may precede its checkpoint
    summary = read_summary(run_dir)
    write_json(path, {**summary, "epochs": epoch, "finished": False, "interrupted": signal,
                      "resume": suggested("train", "--resume", Path(run_dir))})


def checkpoint_path(run_dir: Path, which: str) -> Path:
    """`run_dir/checkpoints/{best,last}.pt`."""
    return Path(run_dir) / "checkpoints" / f"{which}.pt"


def read_config(run_dir: str | Path) -> TrainConfig:
    """The resolved config of an existing run (for `--resume`).

    A config written before `model_options` existed (flat model fields) is upgraded.

    Raises:
        ValueError: no run there, or a config that no longer validates.
    """
    path = Path(run_dir) / CONFIG
    if not path.is_file():
        raise ValueError(f"{run_dir} is not a run folder (no {CONFIG})")
    return TrainConfig(**pin_stored_solver(upgrade_train_fields(_json_object(path))))


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write JSON atomically (non-finite floats as null, so the file stays valid JSON)."""
    atomic_text(path, json.dumps(jsonable(data), indent=2) + "\n")


def add_to_summary(run_dir: str | Path, fields: dict[str, Any]) -> None:
    """Add facts that the caller knows and the loop does not to a finished run's summary."""
    path = Path(run_dir) / SUMMARY
    write_json(path, {**_json_object(path), **fields})


def append_metrics(run_dir: Path, row: dict[str, Any]) -> None:
    """Append an epoch's row (one that a kill cuts short is dropped on resume; one that a
    full disk cuts short is taken back at once, so that a resume reads the file)."""
    path, line = Path(run_dir) / METRICS, (json.dumps(jsonable(row)) + "\n").encode()
    with open(path, "ab", buffering=0) as f:
        size = f.tell()
        try:
            while line:
                line = line[f.write(line):]
        except OSError as exc:
            f.truncate(size)
            raise OSError(exc.errno, exc.strerror, str(path)) from None  # naming the file


def read_metrics(run_dir: str | Path) -> list[dict[str, Any]]:
    """A run's metrics rows.

    Raises:
        ValueError: a line that is not a row (a damaged run folder).
    """
    path = Path(run_dir) / METRICS
    return metrics_rows(read_text(path, ""), path) if path.is_file() else []


def metrics_rows(text: str, path: Path) -> list[dict[str, Any]]:
    """The rows of metrics.jsonl's `text` (read from `path`, which errors name)."""
    rows = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            row = None
        if not (isinstance(row, dict) and isinstance(row.get("epoch"), int)):
            raise ValueError(f"{path}:{lineno} is not a row of metrics (a JSON object with "
                             "its epoch): a damaged run folder")
        rows.append(row)
    return rows


def truncate_metrics(run_dir: Path, last_epoch: int,
                     rows: list[dict[str, Any]] | None = None) -> None:
    """Drop rows after `last_epoch` (of `rows`, if given, else of the file's): an interrupt
    may land between a row and its checkpoint."""
    rows = [r for r in (read_metrics(run_dir) if rows is None else rows)
            if r["epoch"] <= last_epoch]
    atomic_text(Path(run_dir) / METRICS, "".join(json.dumps(r) + "\n" for r in rows))


def seconds_per_epoch(run_dir: Path) -> float | None:
    """Mean wall time of the trained epochs (epoch 0 only validates)."""
    seconds = [r["seconds"] for r in read_metrics(run_dir) if r["epoch"] > 0]
    return sum(seconds) / len(seconds) if seconds else None


def read_summary(run_dir: str | Path) -> dict[str, Any]:
    """A run's summary; for an unfinished run, what its metrics say so far.

    Raises:
        ValueError: not a run folder.
    """
    run_dir = Path(run_dir)
    path = run_dir / SUMMARY
    if path.is_file():
        return _json_object(path)
    if not (run_dir / CONFIG).is_file():
        raise ValueError(f"{run_dir} is not a run folder (no {CONFIG})")
    config = _json_object(run_dir / CONFIG)
    rows = [r for r in read_metrics(run_dir) if r.get("val_loss") is not None]
    summary: dict[str, Any] = {"run_dir": str(run_dir), "model": config.get("model"),
                               "finished": False, "test": None}
    if rows:
        best = min(rows, key=lambda r: r["val_loss"])
        summary |= {
            "best_epoch": best["epoch"], "min_val_loss": best["val_loss"],
            "min_val_mse": best.get("val_mse"), "table2": best["epoch"] * best["val_loss"],
            "epochs": rows[-1]["epoch"],
            "seconds_per_epoch": seconds_per_epoch(run_dir),
        }  # fmt: skip
    return summary


def _json_object(path: Path) -> dict[str, Any]:
    """A run folder's JSON record (config, summary).

    Raises:
        ValueError: a file that cannot be read, is not JSON, or holds no JSON object.
    """
    value = read_json(path)
    if not isinstance(value, dict):
        raise ValueError(f"{path} holds no JSON object: a damaged run folder")
    return value

