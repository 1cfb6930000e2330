"""`mpnode train DATASET...` and `mpnode finetune CHECKPOINT DATASET...`: one training loop, two
doors.

The commands only parse: options left out stay out, so `TrainConfig` and the models'
declared options hold the only defaults; a `--config` TOML file sits beneath the options.
The model options (`--hidden`, `--message-dim`, ...) are built from the registry's
declarations (`mpnode_cli.models.options`), one per option any model declares; the chosen
model refuses the ones it does not declare. `--resume RUN_DIR` rebuilds the
run's own config (only `--epochs`, `--device`, `--plots` and `--stream` may change), from
any folder: the run knows its datasets' absolute paths, and datasets given beside
`--resume` are accepted when their fingerprints are the run's. Several datasets are
trained on at once (`mpnode_cli.data.pooled`). Exit codes: 2 for usage errors,
1 when training diverged, 130 for Ctrl-C and 143 for SIGTERM (both after saving `last.pt`
and a `summary.json` that says the run was interrupted).
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import typer
from pydantic.fields import FieldInfo

from mpnode_cli.cli.common import (
    THREADS,
    console,
    error_message,
    fail,
    solver_option,
    speaks,
    warn,
)
from mpnode_cli.config import train_solver
from mpnode_cli.models.registry import OPTIONS
from mpnode_cli.threads import applied_threads

# Options shared by both commands, declared once (typer reads them as plain defaults).
_CONFIG = typer.Option(None, "--config", help="TOML (or JSON) file of train config fields.")
_RECIPE = typer.Option(
    None, help="Where options left out come from: mpnode (default; measured, plus the "
    "dataset's system recommendation) or paper (the paper's exact choices).")
_LOSS = typer.Option(None, help="mse (recipe default) or huber (δ=1, summed along time).")
_LR = typer.Option(None, help="Adam learning rate (default 1e-3).")
_MIN_LR = typer.Option(None, help="Lowest lr any schedule reaches (default 1e-6).")
_SCHEDULE = typer.Option(
    None, help="lr schedule: plateau (default; halve after --patience epochs without "
    "gain), cosine (to --min-lr over --epochs) or constant.")
_BATCH = typer.Option(None, help="Trajectories per step (default 32; paper recipe 128).")
_EVEN = typer.Option(
    None, "--even-batches/--tail-batch",
    help="Equal-size batches each epoch (default), or full ones and a partial last one.")
_VAL_BATCH = typer.Option(None, help="Trajectories per validation rollout (default 1024).")
_CLIP = typer.Option(None, help="Global gradient-norm clip (default 500).")
_PATIENCE = typer.Option(
    None, help="Plateau schedule: epochs without validation gain before the lr halves (50).")
_NOISE = typer.Option(None, help="Gaussian noise std on normalized train data (1e-4).")
_EPOCHS = typer.Option(None, help="Epochs to train (default 4000; on --resume, the total).")
_FINETUNE_EPOCHS = typer.Option(None, help="Epochs to train (default 4000).")
_JSON = typer.Option(False, "--json", help="Print the summary as one JSON object on stdout.")
_SEED = typer.Option(None, help="Seed of initialization, shuffling and noise (default 0).")
_DEVICE = typer.Option(None, help="cpu (default) or cuda.")
_RUN_DIR = typer.Option(None, help="Run folder (default runs/<dataset>-<model>-<time>).")
_METHOD, _RTOL, _ATOL, _FIXED_DT = (solver_option(name, train_solver())
                                    for name in ("method", "rtol", "atol", "fixed_dt"))
_CURRICULUM = typer.Option(
    None, "--horizon-curriculum/--no-horizon-curriculum",
    help="Train on growing prefixes of the trajectories (default: on for more than 60 "
    "samples per trajectory).")
_CURR_START = typer.Option(None, help="Curriculum: samples in the first epoch (default 5).")
_CURR_EPOCHS = typer.Option(None, help="Curriculum: epochs to reach the full horizon (100).")
_BAD_STEPS = typer.Option(None, help="Bad batches in a row before a rollback (default 5).")
_PLOTS = typer.Option(None, "--plots/--no-plots", help="Draw test plots at the end (on).")
_TRAJECTORIES = typer.Option(
    None, help="Use only the first K train trajectories (all of them, with a warning, where a "
    "dataset has fewer).")
_STREAM = typer.Option(
    None, "--stream/--in-memory",
    help="Read batches from the dataset file as they are needed (a thread reads two "
    "ahead), for datasets larger than memory; same losses as in memory (the default).")


def train_command(
    datasets: list[Path] | None = typer.Argument(
        None, help="One or more mpnode datasets (.h5); several (one system and per-node "
        "sizes, any N and graphs, one dt) are trained on at once, each batch from one of "
        "them. Optional with --resume.", show_default=False, metavar="DATASET"),
    resume: Path | None = typer.Option(None, help="Continue the run in this folder."),
    model: str | None = typer.Option(
        None, help=f"The model: {', '.join(OPTIONS)} (default mpnode)."),
    config_file: Path | None = _CONFIG, recipe: str | None = _RECIPE,
    loss: str | None = _LOSS, lr: float | None = _LR,
    min_lr: float | None = _MIN_LR, schedule: str | None = _SCHEDULE,
    batch_size: int | None = _BATCH, even_batches: bool | None = _EVEN,
    val_batch_size: int | None = _VAL_BATCH,
    clip: float | None = _CLIP, patience: int | None = _PATIENCE,
    noise: float | None = _NOISE, epochs: int | None = _EPOCHS, seed: int | None = _SEED,
    device: str | None = _DEVICE, run_dir: Path | None = _RUN_DIR,
    method: str | None = _METHOD, rtol: float | None = _RTOL, atol: float | None = _ATOL,
    fixed_dt: float | None = _FIXED_DT, horizon_curriculum: bool | None = _CURRICULUM,
    curriculum_start: int | None = _CURR_START, curriculum_epochs: int | None = _CURR_EPOCHS,
    max_bad_steps: int | None = _BAD_STEPS, plots: bool | None = _PLOTS,
    trajectories: int | None = _TRAJECTORIES, stream: bool | None = _STREAM,
    threads: str | None = THREADS, json_out: bool = _JSON,
    **model_options: Any,
) -> None:
    """Train a model on a dataset's train split, or on several datasets' at once (fitted on
    their train splits pooled; validation and test reported per dataset and pooled, the
    best epoch chosen by the pooled validation loss); results go to runs/<name>/."""
    options = _given(locals(), exclude=("datasets", "resume", "config_file", "model_options",
                                        "threads", "json_out"))
    chosen = _given(model_options, exclude=())  # model options given
    try:
        if resume is not None:
            from mpnode_cli.training.resume import resume_config

            config = resume_config(resume, datasets or None, options | chosen)
        else:
            if not datasets:
                raise ValueError("give a DATASET to train on (or --resume RUN_DIR)")
            config = _config(config_file, {**options, "dataset": datasets}, chosen)
    except ValueError as exc:
        fail(error_message(exc))
    _run(config, resume=resume is not None, json_out=json_out)


def _model_option_parameters() -> list[inspect.Parameter]:
    """One CLI option per model option the registry's models declare.

    An option that several models declare appears once; its help is the first model's
    description, the choices of a `Literal`, and the models that take it with their
    defaults. Models must agree on an option's type.
    """
    fields: dict[str, tuple[FieldInfo, list[str]]] = {}
    for kind, declared in OPTIONS.items():
        for name, field in declared.model_fields.items():
            first, takers = fields.setdefault(name, (field, []))
            if field.annotation != first.annotation:
                raise TypeError(f"model option '{name}' has two types: {first.annotation} "
                                f"and {field.annotation} ({kind})")
            takers.append(f"{kind} ({_shown(field.default)})")
    params = []
    for name, (field, takers) in fields.items():
        # Choices are checked with the rest of the options, so that a bad one is refused
        # in the same one line (click would draw its own error box).
        choices = get_args(field.annotation) if get_origin(field.annotation) is Literal else ()
        value_type = str if choices else field.annotation
        if value_type not in (bool, int, float, str):
            raise TypeError(f"model option '{name}' has a type the CLI cannot take: "
                            f"{field.annotation}")
        flag = "--" + name.replace("_", "-")
        decls = [f"{flag}/--no-{flag[2:]}"] if value_type is bool else [flag]
        help_text = " ".join(part for part in (
            field.description,
            f"Choices: {', '.join(choices)}." if choices else None,
            f"Models (default): {', '.join(takers)}.",
        ) if part)
        option = typer.Option(None, *decls, help=help_text, rich_help_panel="Model options")
        params.append(inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=option,
                                        annotation=value_type | None))
    return params


def _shown(value: Any) -> str:
    if isinstance(value, bool):
        return "on" if value else "off"
    return f"{value:g}" if isinstance(value, float) else str(value)


def _with_model_options(command):
    """Give `command` (whose `**model_options` collects them) the model options' parameters."""
    signature = inspect.signature(command)
    fixed = [p for p in signature.parameters.values() if p.kind is not p.VAR_KEYWORD]
    command.__signature__ = signature.replace(parameters=fixed + _model_option_parameters())
    return command


train_command = _with_model_options(train_command)


def finetune_command(
    checkpoint: Path = typer.Argument(..., help="The checkpoint to start from (.pt)."),
    datasets: list[Path] = typer.Argument(
        ..., help="The dataset to finetune on (.h5), or several at once (as train takes "
        "them).", metavar="DATASET"),
    renormalize: bool = typer.Option(
        False, "--renormalize", help="Fit the normalization on the new data."),
    allow_other_system: bool = typer.Option(
        False, "--allow-other-system",
        help="Accept a dataset of another system than the checkpoint was trained on."),
    config_file: Path | None = _CONFIG, recipe: str | None = _RECIPE,
    loss: str | None = _LOSS, lr: float | None = _LR,
    min_lr: float | None = _MIN_LR, schedule: str | None = _SCHEDULE,
    batch_size: int | None = _BATCH, even_batches: bool | None = _EVEN,
    val_batch_size: int | None = _VAL_BATCH,
    clip: float | None = _CLIP, patience: int | None = _PATIENCE,
    noise: float | None = _NOISE, epochs: int | None = _FINETUNE_EPOCHS,
    seed: int | None = _SEED,
    device: str | None = _DEVICE, run_dir: Path | None = _RUN_DIR,
    method: str | None = _METHOD, rtol: float | None = _RTOL, atol: float | None = _ATOL,
    fixed_dt: float | None = _FIXED_DT, horizon_curriculum: bool | None = _CURRICULUM,
    curriculum_start: int | None = _CURR_START, curriculum_epochs: int | None = _CURR_EPOCHS,
    max_bad_steps: int | None = _BAD_STEPS, plots: bool | None = _PLOTS,
    trajectories: int | None = _TRAJECTORIES, stream: bool | None = _STREAM,
    threads: str | None = THREADS, json_out: bool = _JSON,
) -> None:
    """Train from a checkpoint's weights and architecture on another dataset, or on several
    at once (a new run).

    CHECKPOINT may be a run folder (its checkpoints/best.pt).
    """
    options = _given(locals(), exclude=("checkpoint", "datasets", "config_file", "threads",
                                        "json_out"))
    from mpnode_cli.training.checkpoint import resolve_path

    try:
        config = _config(config_file, {**options, "dataset": datasets,
                                       "init_checkpoint": resolve_path(checkpoint)})
    except (ValueError, FileNotFoundError) as exc:
        fail(error_message(exc))
    _run(config, resume=False, json_out=json_out)


def _given(values: dict[str, Any], exclude: tuple[str, ...]) -> dict[str, Any]:
    return {k: v for k, v in values.items() if v is not None and k not in exclude}


# The options that fill the config's `solver` table.
_SOLVER = ("method", "rtol", "atol", "fixed_dt")


def _config(config_file: Path | None, options: dict[str, Any],
            model_options: dict[str, Any] | None = None):
    """The train config: the file's fields (upgraded if written by an earlier version),
    beneath the options given; model options and solver options are merged into the file's
    `[model_options]` and `[solver]` tables one by one."""
    from mpnode_cli.config import TrainConfig, read_config_file, upgrade_train_fields

    fields = upgrade_train_fields(read_config_file(config_file)) if config_file else {}
    solver = {k: v for k, v in options.items() if k in _SOLVER}
    options = {k: v for k, v in options.items() if k not in _SOLVER}
    for table, given in (("model_options", model_options), ("solver", solver)):
        in_file = fields.get(table, {})
        if given and isinstance(in_file, dict):  # else TrainConfig says what is wrong
            fields[table] = in_file | given
    return TrainConfig(**{**fields, **options})


def _run(config: Any, resume: bool, json_out: bool = False) -> None:
    """Train with a progress display, then print the summary table (or JSON)."""
    import json
    from dataclasses import asdict

    from mpnode_cli.report.tables import train_table
    from mpnode_cli.signals import exit_code, interrupt_on_signals, signal_name
    from mpnode_cli.training.distributed import process_group
    from mpnode_cli.training.loop import TrainingDiverged, TrainingInterrupted, train
    from mpnode_cli.training.run import add_to_summary, read_summary

    display_console = console(stderr=True)
    try:
        # Under torchrun: join the other processes; only rank 0 reports (and returns a summary).
        with interrupt_on_signals(), process_group(config.device) as world, _Display(
                display_console, world.main) as display:
            summary = train(config, resume=resume, progress=display.on_event)
    except (ValueError, FileNotFoundError) as exc:
        fail(error_message(exc))
    except TrainingDiverged as exc:
        fail(f"training diverged: {exc}", code=1)
    except TrainingInterrupted as exc:
        if not speaks():
            raise typer.Exit(code=exit_code(exc.cause)) from None
        typer.echo(f"Interrupted ({signal_name(exc.cause)}): saved {exc.run_dir}/checkpoints/"
                   f"last.pt (epoch {exc.epoch}); continue with: mpnode train --resume "
                   f"{exc.run_dir}", err=True)
        raise typer.Exit(code=exit_code(exc.cause)) from None
    except KeyboardInterrupt as exc:
        if speaks():
            typer.echo(f"Interrupted ({signal_name(exc)}) before training started: nothing to "
                       "resume", err=True)
        raise typer.Exit(code=exit_code(exc)) from None
    if summary is None:  # a torchrun process other than rank 0
        return
    if threads := applied_threads():  # beside wall_seconds, which it explains
        add_to_summary(summary.run_dir, {"threads": threads.count})
    if json_out:
        typer.echo(json.dumps(read_summary(summary.run_dir)))
        return
    console().print(train_table(asdict(summary)))


class _Display:
    """A rich progress display fed by the loop's events; epoch lines go above the bars."""

    def __init__(self, out, shown: bool = True):
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        self.console = out
        # No bars when stderr is not a terminal (pipes, logs, tests); epoch lines remain.
        self.bar = Progress(TextColumn("{task.description}"), BarColumn(),
                            MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
                            TextColumn("{task.fields[info]}"), console=out,
                            transient=True, disable=not (shown and out.is_terminal))
        self.epochs = self.bar.add_task("epochs", total=None, info="")
        self.batches = self.bar.add_task("batches", total=None, info="")
        self.every, self.last_epoch, self.best = 1, 0, float("inf")

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        return self.bar.__exit__(*exc)

    def on_event(self, event: dict[str, Any]) -> None:
        kind = event["event"]
        if kind == "start":
            self.last_epoch = event["epochs"]
            self.every = max(1, event["epochs"] // 20)
            self.bar.update(self.epochs, total=event["epochs"], completed=event["first_epoch"] - 1)
            self.bar.update(self.batches, total=event["batches"], completed=0)
            self.console.print(f"run {event['run_dir']}: {event['parameters']:,} parameters, "
                               f"epochs {event['first_epoch']}–{event['epochs']}")
            if threads := applied_threads():
                self.console.print(f"threads: {threads.describe()}")
            if "solver" in event:
                self.console.print(f"solver: {event['solver']}")
            if event.get("stream"):
                self.console.print("data: streamed from the file, two batches read ahead")
            if event.get("processes", 1) > 1:
                self.console.print(f"processes: {event['processes']} ({event['backend']}), "
                                   "each training its slice of every batch")
        elif kind == "batch":
            self.bar.update(self.batches, completed=event["batch"],
                            info=f"loss {event['loss']:.4g}")
        elif kind == "epoch":
            self._epoch(event)
        elif kind == "skip":
            self.console.print(f"[yellow]epoch {event['epoch']} batch {event['batch']}: "
                               f"update skipped ({event['reason']})")
        elif kind == "restore":
            self.console.print(f"[yellow]epoch {event['epoch']}: rolled back to the last "
                               f"good epoch, lr now {event['lr']:.3g}")
        elif kind == "test":
            self.bar.update(self.batches, description="testing", completed=0)
        elif kind == "warning":
            warn(event["text"])

    def _epoch(self, row: dict[str, Any]) -> None:
        from mpnode_cli.report.tables import fmt

        epoch, val = row["epoch"], row["val_loss"]
        self.best = min(self.best, val) if val is not None else self.best
        info = f"val {fmt(val)} · best {fmt(self.best)} · lr {row['lr']:.2g}"
        self.bar.update(self.epochs, completed=epoch, info=info)
        self.bar.update(self.batches, completed=0)
        if epoch % self.every == 0 or epoch == self.last_epoch:
            each = "".join(f" {name} {fmt(mse)}"  # several datasets: each one's MSE
                           for name, mse in row.get("val_mse_by_dataset", {}).items())
            self.console.print(f"epoch {epoch:>4}  train {fmt(row['train_loss']):>7}  "
                               f"val {fmt(val):>7} (MSE {fmt(row['val_mse']):>7}{each})  "
                               f"lr {row['lr']:.2g}  {row['seconds']:.2f}s  "
                               f"{row['rhs_evals']} evals")
