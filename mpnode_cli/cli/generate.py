"""`mpnode generate SYSTEM [options]`: simulate ground truth and write an HDF5 dataset.

The command only parses: it layers a preset, a config file and the options given (later
wins), builds a `GenerateConfig`, calls `mpnode_cli.data.generate.generate`, and turns the
result or the error into output and an exit code (2 for usage errors, 1 for numerical
failure, 130 for Ctrl-C, 143 for SIGTERM; either leaves nothing behind). Before a big job
it prints the size and memory it will take and, above `common.CONFIRM_BYTES`, asks to go
on (`--yes` answers for a script). torch and h5py are imported inside the function.
"""

from __future__ import annotations

import inspect
import math
from pathlib import Path
from typing import Any

import typer

from mpnode_cli.cli.common import (
    FORCE,
    JSON_OUT,
    THREADS,
    YES,
    confirm_size,
    output_parser,
    solver_option,
    warn,
    with_bar,
)
from mpnode_cli.cli.common import error_message as _message
from mpnode_cli.cli.common import fail as _usage_error
from mpnode_cli.cli.generate_summary import print_json, print_summary
from mpnode_cli.cli.options import field_default, field_parameter, in_panel, with_options
from mpnode_cli.config.fields import generate_solver
from mpnode_cli.config.generate import GenerateConfig


def _complete_system(incomplete: str) -> list[str]:
    from mpnode_cli.systems.registry import SYSTEMS

    return [name for name in SYSTEMS if name.startswith(incomplete)]


def _complete_preset(incomplete: str) -> list[str]:
    from mpnode_cli.data.presets import PRESETS

    return [name for name in PRESETS if name.startswith(incomplete)]


def _system_names() -> str:
    from mpnode_cli.systems.registry import SYSTEMS

    return ", ".join(SYSTEMS)


def _topologies() -> str:
    from mpnode_cli.systems.registry import SYSTEMS

    return ", ".join(dict.fromkeys(t for cls in SYSTEMS.values() for t in cls.topologies))


def _grid_systems() -> str:
    from mpnode_cli.systems.registry import grid_systems

    return ", ".join(grid_systems())


def _parameters() -> str:
    """Each built-in system's parameters and defaults; the graph parameters that the
    Barzel–Barabási family shares are named once, after them."""
    from mpnode_cli.systems.barzel_barabasi import GRAPH_DEFAULTS, BarzelBarabasi
    from mpnode_cli.systems.registry import SYSTEMS

    own = "; ".join(f"{cls.name} " + ", ".join(f"{k} ({v:g})" for k, v in cls.defaults.items()
                                               if not issubclass(cls, BarzelBarabasi)
                                               or k not in GRAPH_DEFAULTS)
                    for cls in SYSTEMS.values())
    family = [cls.name for cls in SYSTEMS.values() if issubclass(cls, BarzelBarabasi)]
    return (f"{own}; and {', '.join(family)} take the graph's "
            + ", ".join(f"{k} ({v:g})" for k, v in GRAPH_DEFAULTS.items()))


# The command's own declarations; its other options are `GenerateConfig`'s fields and the
# solver's (`_field`), in `_PANELS`.
_SYSTEM = typer.Argument(
    None,
    help=f"{_system_names()}, or your own with --system-file (may come from --preset "
    "or --config).",
    autocompletion=_complete_system,
    show_default=False,
)
_PRESET = typer.Option(
    None,
    help="Start from one of the paper's datasets, e.g. lorenz10, gene-ba-8x8.",
    autocompletion=_complete_preset,
)
_CONFIG = typer.Option(
    None, "--config", help="TOML (or JSON) file of config fields; options override it."
)
_PARAM = typer.Option(
    None,
    "--param",
    "-p",
    metavar="NAME=VALUE",
    help=f"System parameter or option NAME=VALUE, e.g. -p K=0.5 (repeatable). "
    f"Parameters (default): {_parameters()}.",
)
GRAPHS, TRAJECTORIES, SOLVER, RUN, SYSTEM = (
    "Graphs", "Trajectories", "Solver", "Input, output and run", "System options")
_PANELS = {
    GRAPHS: ("nodes", "grid", "topology", "graphs", "graph_seed", "edge_list", "directed",
             "hubs", "hub_multiplicity"),
    TRAJECTORIES: ("trajectories", "t_end", "dt", "seed", "split"),
    SOLVER: ("method", "rtol", "atol", "fixed_dt", "chunk_size"),
    RUN: ("system_file", "preset", "config_file", "out", "shard", "dtype", "force", "yes",
          "json_out", "threads"),
    SYSTEM: ("param",),
}
_SOLVER = ("method", "rtol", "atol", "fixed_dt")
# Counts, given as 1000, 1_000 or 1e3 (`_whole`), and their metavars.
_COUNTS = {"nodes": "N", "grid": "N", "graphs": "N", "trajectories": "N", "chunk_size": "N",
           "hubs": "H", "hub_multiplicity": "W"}


def generate_command(
    system: str | None = _SYSTEM,
    preset: str | None = _PRESET,
    config_file: Path | None = _CONFIG,
    force: bool = FORCE,
    yes: bool = YES,
    json_out: bool = JSON_OUT,
    param: list[str] | None = _PARAM,
    threads: str | None = THREADS,
    **options: Any,
) -> None:
    """Simulate ground truth on graphs and write an HDF5 dataset."""
    given = {k: v for k, v in options.items() if k in GenerateConfig.model_fields}
    solver = {k: v for k, v in options.items() if k in _SOLVER}
    system_options = {k: v for k, v in options.items() if k not in given and k not in solver}
    try:
        fields = _command_line({"system": system, **given}, solver, param or [],
                               system_options)
        config = _layered_config(preset, config_file, given.get("system_file"), fields)
    except ValueError as exc:
        _usage_error(_message(exc))
    _run(config, force, yes, json_out, config_file)


def _field(name: str, panel: str) -> inspect.Parameter | None:
    """The option of `GenerateConfig`'s field `name`, or of the solver's with
    `generate_solver()`'s default."""
    if name in _SOLVER:
        return inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY,
                                 annotation=(str if name == "method" else float) | None,
                                 default=in_panel(solver_option(name, generate_solver()), panel))
    extra = {"grid": f"For systems whose nodes sit on a grid ({_grid_systems()}); others "
                     "refuse it (give --nodes).",
             "topology": f"Built in: {_topologies()}."}.get(name, "")
    typed = {"split": str, "shard": str} | dict.fromkeys(_COUNTS, str)
    return field_parameter(
        GenerateConfig, name, panel, default=field_default(GenerateConfig, name), extra=extra,
        metavar=_COUNTS.get(name) or {"shard": "i/n"}.get(name), value_type=typed.get(name),
        decls=("--out", "-o") if name == "out" else None,
        parser=output_parser("--out") if name == "out" else None)


def _command_line(given: dict[str, Any], solver: dict[str, Any], param: list[str],
                  system_options: dict[str, Any]) -> dict[str, Any]:
    """The command line's layer of config fields: the options given (counts as whole
    numbers), the solver's as the config's `solver` table and the system's as `params`.

    Raises:
        ValueError: a count that is not a whole number, a --param that is not NAME=VALUE,
            or a parameter given twice.
    """
    options = {key: value for key, value in given.items() if value is not None}
    for key in _COUNTS:
        if key in options:
            options[key] = _whole(options[key], "--" + key.replace("_", "-"))
    solver = {key: value for key, value in solver.items() if value is not None}
    if solver:  # the config's `solver` table, merged over a config file's
        options["solver"] = solver
    params = _parse_params(param)
    system_options = {k: v for k, v in system_options.items() if v is not None}
    if twice := sorted(set(params) & set(system_options)):
        raise ValueError(f"{twice[0]} is given twice, as --param {twice[0]}=... and as "
                         f"--{twice[0].replace('_', '-')}: give it once")
    params |= system_options
    if params:
        options["params"] = params
    return options


def _layered_config(preset: str | None, config_file: Path | None, system_file: Path | None,
                    options: dict[str, Any]) -> GenerateConfig:
    """The preset, the config file and the command line's `options` (later wins) as a
    `GenerateConfig`; a system file's system is the one generated when none is named.

    Raises:
        ValueError: a system file, preset or config file that does not load, no system,
            or fields the config refuses.
    """
    from mpnode_cli.config.file import read_config_file
    from mpnode_cli.config.upgrade import upgrade_solver_fields
    from mpnode_cli.data.presets import get_preset, merge_layers

    own = None
    if system_file is not None:  # first, so that its presets are known
        from mpnode_cli.systems.registry import load_system_file

        own = load_system_file(system_file).name
    layers = [
        (f"preset {preset}", get_preset(preset) if preset else {}),
        (f"config {config_file}",
         upgrade_solver_fields(read_config_file(config_file)) if config_file else {}),
        ("command line", options),
    ]
    fields = merge_layers(layers)
    if "system" not in fields and own is not None:
        fields["system"] = own
    if "system" not in fields:
        raise ValueError(f"give a SYSTEM ({_system_names()}) or --preset NAME")
    return GenerateConfig(**fields)


def _system_option_parameters() -> list[inspect.Parameter]:
    """One CLI option per option the built-in systems declare (`System.options`), in the
    "System options" panel, with its help and the systems that take it with their
    defaults. The system refuses an option it does not declare; a system of your own
    takes its options as `-p NAME=VALUE`."""
    from mpnode_cli.systems.registry import SYSTEMS

    declared: dict[str, tuple[Any, list[str]]] = {}
    for cls in SYSTEMS.values():
        for name, option in cls.options.items():
            first, takers = declared.setdefault(name, (option, []))
            if bool(option.choices) != bool(first.choices):
                raise TypeError(f"system option '{name}' is a number in one system and a "
                                f"choice in another ({cls.name})")
            takers.append(f"{cls.name} ({option.default:g})" if not option.choices
                          else f"{cls.name} ({option.default})")
    params = []
    for name, (option, takers) in declared.items():
        choices = f" Choices: {', '.join(option.choices)}." if option.choices else ""
        help_text = f"{option.help}{choices} Systems (default): {', '.join(takers)}."
        value_type = str if option.choices else float
        params.append(inspect.Parameter(
            name, inspect.Parameter.KEYWORD_ONLY, annotation=value_type | None,
            default=typer.Option(None, "--" + name.replace("_", "-"), help=help_text,
                                 rich_help_panel=SYSTEM)))
    return params


def _with_system_options(command):
    """Give `command` (whose `**options` collects them) its options in `_PANELS`, then the
    systems' options."""
    command = with_options(command, _PANELS, _field)
    signature = inspect.signature(command)
    fixed = [p for p in signature.parameters.values() if p.kind is not p.VAR_KEYWORD]
    command.__signature__ = signature.replace(parameters=fixed + _system_option_parameters())
    return command


generate_command = _with_system_options(generate_command)


def _run(config: Any, force: bool, yes: bool, json_out: bool,
         config_file: Path | None = None) -> None:
    """Check the job and its output (never one of its inputs, `config_file` included),
    generate with a progress bar, then print the summary."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    from mpnode_cli.data.generate import (
        GenerateError,
        generate,
        generate_inputs,
        output_path,
        resolve_generate_config,
    )
    from mpnode_cli.data.splits import split_counts, split_warning
    from mpnode_cli.paths import check_output_file

    try:  # generate itself builds the graphs before solving: no dry run here
        config = resolve_generate_config(config, dry_run=False)
        _confirm_size(config, yes)
        check_output_file(output_path(config), overwrite=force,
                          inputs=(*generate_inputs(config), config_file))
    except (FileExistsError, ValueError) as exc:
        _usage_error(_message(exc))
    # Before solving, so that it can be stopped; the whole dataset's split, shard or not.
    empty = split_warning(split_counts(config.trajectories, config.split), config.split)
    if empty:
        warn(empty)
    columns = (
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )

    def work(progress):  # each step's name on the bar, from the graphs to the file
        return generate(config, overwrite=force, progress=progress,
                        stage=lambda step: progress(None, None, f"{config.system}: {step}"))

    summary = with_bar(f"{config.system}: starting", work,
                       quiet=json_out, stopped=f"nothing written to {output_path(config)}",
                       failures=(GenerateError,), columns=columns, total=config.trajectories)
    if json_out:
        print_json(config, summary)
    else:
        print_summary(config, summary)


def _confirm_size(config: Any, yes: bool) -> None:
    """`confirm_size` of a resolved config's job (its shard's, for a shard).

    Raises:
        ValueError: as `confirm_size`.
    """
    from mpnode_cli.data.generate import estimate, trajectory_range

    start, stop = trajectory_range(config)
    confirm_size(estimate(config), f"{stop - start} trajectories × {config.num_steps + 1} "
                 f"samples × {config.nodes} nodes", yes)


def _whole(text: str, option: str) -> int:
    """A count given as `1000`, `1_000` or `1e3` (a whole number however it is written)."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or not value.is_integer():
        raise ValueError(f"{option} expects a whole number, got {text!r}")
    return int(value)


def _parse_params(items: list[str]) -> dict[str, float | str]:
    """`["K=0.5", "init=hotspot"]` → `{"K": 0.5, "init": "hotspot"}` (numbers as floats)."""
    params: dict[str, float | str] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--param expects NAME=VALUE, got {item!r}")
        if name in params:
            raise ValueError(f"--param {name} is given twice: give it once")
        try:
            params[name] = float(value)
        except ValueError:
            params[name] = value
    return params
