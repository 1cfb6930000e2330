"""`mpnode train DATASET...` and `mpnode finetune CHECKPOINT DATASET...`: one training loop, two
doors.

The commands only parse: options left out stay out, so `TrainConfig` and the models'
declared options hold the only defaults; a `--config` TOML file sits beneath the options.
Every option is built from a declaration: a `TrainConfig` field's (its description is the
help; its default, and the recipes' where they differ, are shown), a solver option's
(`SolverOptions`), or a model option's (`mpnode_cli.models.options`: one per option any
model declares; the chosen model refuses the ones it does not declare). `--help` groups
them in panels, as a user looks for them. `--resume RUN_DIR` continues a run as its folder
says (`mpnode_cli.training.resume`: what may change, and which datasets and config file
it takes). Several
datasets are trained on at once (`mpnode_cli.data.pooled`). Exit codes: 2 for usage
errors, 1 when training diverged, 130 for Ctrl-C and 143 for SIGTERM (both after saving
`last.pt` and a `summary.json` that says the run was interrupted).
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import typer
from pydantic.fields import FieldInfo

from mpnode_cli import flags
from mpnode_cli.cli.common import (
    JSON_OUT,
    THREADS,
    console,
    error_message,
    fail,
    output_parser,
    solver_option,
    speaks,
)
from mpnode_cli.cli.options import (
    choices,
    field_parameter,
    in_panel,
    parameter,
    plain,
    shown,
    with_options,
)
from mpnode_cli.cli.train_display import TrainingDisplay, TrainingStep
from mpnode_cli.config.fields import train_solver
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.models.registry import OPTIONS
from mpnode_cli.solver.options import SolverOptions
from mpnode_cli.terminal import suggested
from mpnode_cli.threads import applied_threads
from mpnode_cli.training.recipe import CURRICULUM_MIN_SAMPLES, recipe_values
from mpnode_cli.training.resume import resumable_options

# The panels of `--help`, as a user looks for an option. The curriculum's three have their
# own: `--no-horizon-curriculum` widens a panel's columns until its help is cut to a sliver.
DATA, RECIPE, CURRICULUM, SOLVER, RUN, MODEL = (
    "Data", "Recipe and optimization", "Horizon curriculum", "Solver", "Output and run",
    "Model options")

# The solver options, which fill the config's `solver` table (`train_solver()`'s defaults).
_SOLVER = ("method", "rtol", "atol", "fixed_dt", "max_steps")

# Every option of the two commands, by panel, in the order shown (the model options follow
# `model`). A `TrainConfig` field or a solver option is built from its declaration; the
# other names are the command's own parameters. A command has the ones it takes.
_PANELS = {
    DATA: ("renormalize", "allow_other_system", "allow_predictions", "trajectories",
           "stream", "for_graphs", "for_in_degree", "system_file"),
    RECIPE: ("recipe", "loss", "epochs", "batch_size", "even_batches", "lr", "min_lr",
             "schedule", "patience", "stop_patience", "time_limit", "clip", "noise",
             "max_bad_steps", "val_batch_size", "seed", "seeds", "wrap_angles",
             "balance_datasets"),
    CURRICULUM: ("horizon_curriculum", "curriculum_start", "curriculum_epochs"),
    SOLVER: _SOLVER,
    RUN: ("run_dir", "resume", "config_file", "device", "dtype", "memory_budget", "threads",
          "plots", "json_out"),
    MODEL: ("model",),
}

# Every system declares the loss of the paper recipe (`System.paper_loss`).
_SYSTEM_CHOOSES = {"loss"}


_CONFIG = typer.Option(None, "--config", help="TOML (or JSON) file of train config fields.")


def train_command(
    datasets: list[Path] | None = typer.Argument(
        None, help="One or more mpnode datasets (.h5); several (one system and per-node "
        "sizes, any N and graphs, one dt) are trained on at once, each batch from one of "
        "them. Optional with --resume.", show_default=False, metavar="DATASET"),
    resume: Path | None = typer.Option(
        None, help="Continue the run in this folder, as configured: only "
        f"{resumable_options()} may change."),
    for_graphs: list[Path] | None = typer.Option(
        None, "--for-graphs", metavar="TARGET", show_default=False,
        help=TrainConfig.model_fields["for_graphs"].description + " Repeat for several."),
    for_in_degree: int | None = typer.Option(
        None, min=1, show_default=False,
        help=TrainConfig.model_fields["for_in_degree"].description),
    system_file: Path | None = typer.Option(
        None, show_default=False, help=TrainConfig.model_fields["system_file"].description),
    config_file: Path | None = _CONFIG, threads: str | None = THREADS,
    json_out: bool = JSON_OUT, **options: Any,
) -> None:
    """Train a model on a dataset's train split, or on several datasets' at once (fitted on
    their train splits pooled; validation and test reported per dataset and pooled, the
    best epoch chosen by the pooled validation loss); results go to runs/<name>/.

    For larger graphs: --for-graphs TARGET (or --for-in-degree K) adds degree-coverage data
    that reach the targets' hubs, simulated from the dataset's own system."""
    fields, chosen = _given(options)
    fields |= {k: v for k, v in (("for_graphs", for_graphs), ("for_in_degree", for_in_degree),
                                 ("system_file", system_file)) if v}
    try:
        if resume is not None:
            from mpnode_cli.training.resume import resume_config

            config = resume_config(resume, datasets or None, fields | chosen, config_file)
        else:
            if not datasets:
                raise ValueError("give a DATASET to train on (or --resume RUN_DIR)")
            config = train_config_from(config_file, {**fields, "dataset": datasets}, chosen)
    except ValueError as exc:
        fail(error_message(exc))
    _run(config, resume=resume is not None, json_out=json_out)


def finetune_command(
    checkpoint: Path = typer.Argument(..., help="The checkpoint to start from (.pt).",
                                      metavar="CHECKPOINT"),
    datasets: list[Path] = typer.Argument(
        ..., help="The dataset to finetune on (.h5), or several at once (as train takes "
        "them).", metavar="DATASET"),
    config_file: Path | None = _CONFIG, threads: str | None = THREADS,
    json_out: bool = JSON_OUT, **options: Any,
) -> None:
    """Train from a checkpoint's weights and architecture on another dataset, or on several
    at once (a new run).

    CHECKPOINT may be a run folder (its checkpoints/best.pt).
    """
    fields, _ = _given(options)
    from mpnode_cli.training.checkpoint import resolve_path

    try:
        config = train_config_from(config_file, {**fields, "dataset": datasets,
                                       "init_checkpoint": resolve_path(checkpoint)})
    except (ValueError, FileNotFoundError) as exc:
        fail(error_message(exc))
    _run(config, resume=False, json_out=json_out)


def _given(options: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """The options given (not None): config and solver fields, and model options."""
    given = {k: v for k, v in options.items() if v is not None}
    model = {k: v for k, v in given.items() if k in _MODEL_OPTIONS}
    return {k: v for k, v in given.items() if k not in model}, model


def train_config_from(config_file: Path | None, options: dict[str, Any],
                      model_options: dict[str, Any] | None = None):
    """The train config: the file's fields (upgraded if written by an earlier version),
    beneath the options given; model options and solver options are merged into the file's
    `[model_options]` and `[solver]` tables one by one."""
    from mpnode_cli.config.file import read_config_file
    from mpnode_cli.config.upgrade import upgrade_train_fields

    fields = upgrade_train_fields(read_config_file(config_file)) if config_file else {}
    solver = {k: v for k, v in options.items() if k in _SOLVER}
    options = {k: v for k, v in options.items() if k not in _SOLVER}
    for table, given in (("model_options", model_options), ("solver", solver)):
        in_file = fields.get(table, {})
        if given and isinstance(in_file, dict):  # else TrainConfig says what is wrong
            fields[table] = in_file | given
    return TrainConfig(**{**fields, **options})


def _with_options(command, leave_out: tuple[str, ...] = (), model_options: bool = False):
    """Give `command` (whose `**options` collects them) its options in `_PANELS`' order: its
    own parameters placed in their panels, an option for each `TrainConfig` field and
    solver option there but those in `leave_out`, and the models' options if
    `model_options`."""
    def build(name: str, panel: str) -> inspect.Parameter | None:
        if name in _SOLVER:
            return _solver_parameter(name, panel)
        if name in TrainConfig.model_fields and name not in leave_out:
            return _field_parameter(name, panel)
        return None

    command = with_options(command, _PANELS, build)
    if model_options:
        signature = inspect.signature(command)
        command.__signature__ = signature.replace(
            parameters=[*signature.parameters.values(), *_model_option_parameters()])
    return command


def _field_parameter(name: str, panel: str) -> inspect.Parameter:
    """The option of `TrainConfig` field `name` (`field_parameter`), its choices the
    registry's models for `model`, with the default a user gets (`_default_shown`)."""
    field = TrainConfig.model_fields[name]
    allowed = tuple(OPTIONS) if name == "model" else None
    decls = flags.decls(name, field.annotation is bool)
    default = _default_shown(name, field, switch="/" not in decls[0])
    parser = output_parser("--run-dir", folder=True) if name == "run_dir" else None
    return field_parameter(TrainConfig, name, panel, default=default, allowed=allowed,
                           decls=decls, parser=parser)


def _default_shown(name: str, field: FieldInfo, switch: bool) -> str | None:
    """The default a user gets: the mpnode recipe's (that is the field's default where the
    recipe leaves it; the dataset's system may recommend another), and the paper recipe's
    where it differs. None where there is nothing to say: a `switch` (a flag with no
    name for off) that is off, a field whose description says what leaving it out does."""
    below, above = (recipe_values("mpnode", {}, n)
                    for n in (CURRICULUM_MIN_SAMPLES - 1, CURRICULUM_MIN_SAMPLES))
    ours = below.get(name, field.default)
    if ours is None or (ours is False and switch):
        return None
    text = shown(ours)
    if above.get(name, ours) != ours:  # the mpnode recipe decides by the trajectories' length
        text = f"{shown(above[name])} from {CURRICULUM_MIN_SAMPLES} samples per trajectory"
    paper = recipe_values("paper", {}, CURRICULUM_MIN_SAMPLES).get(name, field.default)
    if name in _SYSTEM_CHOOSES:
        text += "; paper recipe: the system's"
    elif paper is not None and paper != ours:
        text += f"; paper recipe {shown(paper)}"
    return text


def _solver_parameter(name: str, panel: str) -> inspect.Parameter:
    """The option of `SolverOptions` field `name` with `train_solver()`'s default
    (`solver_option`); its choices are checked with the config, in one line."""
    annotation = SolverOptions.model_fields[name].annotation
    value_type = str if choices(annotation) else plain(annotation)
    return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, annotation=value_type | None,
                             default=in_panel(solver_option(name, train_solver()), panel))


def _model_option_parameters() -> list[inspect.Parameter]:
    """One CLI option per model option the registry's models declare.

    An option that several models declare appears once; its help is the first model's
    description, the choices of a `Literal`, and the models that take it with the default
    a user gets: the mpnode recipe's, and the paper recipe's where it differs. Models must
    agree on an option's type.
    """
    recipes = [recipe_values(name, {}, CURRICULUM_MIN_SAMPLES)["model_options"]
               for name in ("mpnode", "paper")]
    fields: dict[str, tuple[FieldInfo, list[str]]] = {}
    for kind, declared in OPTIONS.items():
        for name, field in declared.model_fields.items():
            first, takers = fields.setdefault(name, (field, []))
            if field.annotation != first.annotation:
                raise TypeError(f"model option '{name}' has two types: {first.annotation} "
                                f"and {field.annotation} ({kind})")
            if name in TrainConfig.model_fields or name in _SOLVER:
                raise TypeError(f"model option '{name}' ({kind}) has the name of a train "
                                "option")
            ours, paper = (shown(r.get(name, field.default)) for r in recipes)
            takers.append(f"{kind} ({ours})" if ours == paper
                          else f"{kind} ({ours}; paper recipe {paper})")
    params = []
    for name, (field, takers) in fields.items():
        # Choices are checked with the rest of the options, so that a bad one is refused
        # in the same one line (click would draw its own error box).
        named = choices(field.annotation)
        value_type = str if named else field.annotation
        help_text = " ".join(part for part in (
            field.description,
            f"Choices: {', '.join(named)}." if named else None,
            f"Models (default): {', '.join(takers)}.",
        ) if part)
        params.append(parameter(name, value_type, flags.decls(name, value_type is bool),
                                help_text, MODEL))
    return params


_MODEL_OPTIONS = {name for declared in OPTIONS.values() for name in declared.model_fields}
# A finetune's model is its checkpoint's; renormalizing and another system are a finetune's.
train_command = _with_options(train_command, leave_out=("renormalize", "allow_other_system"),
                              model_options=True)
finetune_command = _with_options(finetune_command, leave_out=(
    "model", "for_graphs", "for_in_degree", "system_file"))


def _run(config: Any, resume: bool, json_out: bool = False) -> None:
    """Train with a progress display, then print the summary table (or JSON)."""
    import json
    from dataclasses import asdict

    from mpnode_cli.memory import naming_memory
    from mpnode_cli.report.tables import train_table
    from mpnode_cli.signals import exit_code, interrupt_on_signals, signal_name
    from mpnode_cli.training.distributed import process_group
    from mpnode_cli.training.loop import TrainingDiverged, TrainingInterrupted, train
    from mpnode_cli.training.run import add_to_summary, read_summary

    display_console = console(stderr=True)
    step = TrainingStep()
    try:
        # Under torchrun: join the other processes; only rank 0 reports (and returns a summary).
        with interrupt_on_signals(), process_group(config.device) as world, TrainingDisplay(
                display_console, world.main) as display, naming_memory(
                step, None, "lower --batch-size, or train on fewer samples or nodes"):
            summary = train(config, resume=resume, progress=step.told(display.on_event))
    except (ValueError, FileNotFoundError) as exc:
        fail(error_message(exc))
    except TrainingDiverged as exc:
        fail(f"training diverged: {exc}", code=1)
    except TrainingInterrupted as exc:
        if not speaks():
            raise typer.Exit(code=exit_code(exc.cause)) from None
        typer.echo(f"Interrupted ({signal_name(exc.cause)}): saved {exc.run_dir}/checkpoints/"
                   f"last.pt (epoch {exc.epoch}); continue with: "
                   f"{suggested('train', '--resume', Path(exc.run_dir))}", err=True)
        raise typer.Exit(code=exit_code(exc.cause)) from None
    except KeyboardInterrupt as exc:
        if speaks():
            said = (f"the run folder is intact: continue it with "  # its epochs may be the new
                    f"{suggested('train', '--resume', Path(config.run_dir))}" if resume
                    else "nothing to resume")
            typer.echo(f"Interrupted ({signal_name(exc)}) before training started: {said}",
                       err=True)
        raise typer.Exit(code=exit_code(exc)) from None
    if summary is None:  # a torchrun process other than rank 0
        return
    if threads := applied_threads():  # beside wall_seconds, which it explains
        add_to_summary(summary.run_dir, {"threads": threads.count})
    if json_out:
        typer.echo(json.dumps(read_summary(summary.run_dir)))
        return
    console().print(train_table(asdict(summary)))
