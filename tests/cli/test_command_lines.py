"""Command lines from declarations: the `mpnode` lines the reports give for each step
(`experiments.commands`) parse with the real typer app (every option they name exists and
takes the value given), and generate's options are `GenerateConfig`'s fields."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import typer
from conftest import invoke

from mpnode_cli import flags
from mpnode_cli.cli.app import app
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.experiments import commands, spec

# click's usage error (typer ships its own click): unknown options, values of a wrong type.
UsageError = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "UsageError")


def parses(line: str) -> None:
    """Parse `mpnode VERB ...` as the CLI would, without running it (click raises
    `UsageError` for an unknown option or a value of the wrong type)."""
    group = typer.main.get_command(app)
    words = shlex.split(line.split("  # ")[0])
    assert words[0] == "mpnode"
    with group.make_context("mpnode", words[1:], resilient_parsing=True) as parent:
        name, command, rest = group.resolve_command(parent, words[1:])
        assert command is not None, name
        command.make_context(name, rest, parent=parent)


def step_lines(name: str, scale: str) -> list[str]:
    """The command of each generate, train and finetune step of experiment `name`."""
    experiment, lines = spec.load(name), []
    for step in experiment.steps:
        options = spec.resolve(step, scale, "mpnode", seeds=3)
        if step.verb == "generate":
            lines.append(commands.generate_line(step, options, Path("data.h5")))
        elif step.verb in spec.TRAINING:
            checkpoint = Path("parent/best.pt") if step.verb == "finetune" else None
            lines.append(commands.train_line(step, options, Path("data.h5"), Path("run"),
                                             checkpoint))
    return lines


@pytest.mark.parametrize("scale", ["small", "paper"])
@pytest.mark.parametrize("name", spec.names())
def test_every_step_command_of_a_shipped_experiment_parses(name, scale):
    lines = step_lines(name, scale)
    assert lines
    for line in lines:
        parses(line)


def test_a_command_with_an_unknown_option_does_not_parse():
    """The check can fail: an option no verb has, and a number that is not one."""
    with pytest.raises(UsageError):
        parses("mpnode train data.h5 --epoch 3")
    with pytest.raises(UsageError):
        parses("mpnode generate lorenz --dt fast")


@pytest.mark.parametrize("value", [True, False])
def test_every_train_switch_is_spelt_as_the_cli_takes_it(value):
    """Each boolean train option, on and off, as a report would write it: the spelling
    both sides take from `mpnode_cli.flags` parses with the real app."""
    from mpnode_cli.config.train import TrainConfig

    booleans = [n for n, f in TrainConfig.model_fields.items() if f.annotation is bool]
    assert "even_batches" in booleans and "renormalize" in booleans
    for name in booleans:
        head = "mpnode finetune parent.pt data.h5" if name in (
            "renormalize", "allow_other_system") else "mpnode train data.h5"
        parses(" ".join([head, *flags.words(name, value)]))


def _options_of(verb: str) -> dict:
    group = typer.main.get_command(app)
    with group.make_context("mpnode", [verb], resilient_parsing=True) as parent:
        _, command, _ = group.resolve_command(parent, [verb])
    return {p.name: p for p in command.params}


@pytest.mark.parametrize(("verb", "config", "elsewhere"), [
    ("generate", "generate.GenerateConfig", ("system", "params", "solver")),  # argument, -p, own
    ("import", "importer.ImportConfig", ()),
    ("simulate", "simulate.SimulateConfig", ("checkpoint", "member")),  # argument, --member
])
def test_every_config_field_is_an_option_with_its_description_as_help(verb, config, elsewhere):
    """The verbs' options come from their configs' declarations: one per field, its help
    the field's description, required where the field is."""
    import importlib

    module, name = config.split(".")
    fields = getattr(importlib.import_module(f"mpnode_cli.config.{module}"), name).model_fields
    options = _options_of(verb)
    for name, field in fields.items():
        if name in elsewhere:
            continue
        assert flags.flag(name) in options[name].opts, name
        assert options[name].help.startswith(field.description.removesuffix(".")), name
        assert options[name].required == field.is_required(), name
    if verb == "generate":
        assert {"method", "rtol", "atol", "fixed_dt"} <= set(options)


def test_a_count_is_a_whole_number_however_written(tmp_path):
    out = tmp_path / "g.h5"
    result = invoke("generate", "gene", "--nodes", "8", "--topology", "ba", "--hubs", "1e0",
                    "--trajectories", "4", "--t-end", "0.2", "--dt", "0.1", "--out", out)
    assert result.exit_code == 0, result.output
    assert read_dataset(out).config["hubs"] == 1
    result = invoke("generate", "gene", "--hubs", "1.5", "--out", tmp_path / "h.h5")
    assert result.exit_code == 2 and "--hubs expects a whole number" in result.output


@pytest.mark.parametrize("model", ["mpnode", "gnode"])
def test_the_model_options_help_gives_the_defaults_each_recipe_resolves_to(model, user_files):
    """`train --help` names each model option's default under mpnode's recipe and, where
    it differs, the paper's: what a run on a dataset (a user's import, system "custom")
    resolves to."""
    import re

    from mpnode_cli.config.train import TrainConfig
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.recipe import resolve_train_config

    group = typer.main.get_command(app)
    with group.make_context("mpnode", ["train"], resilient_parsing=True) as parent:
        _, command, _ = group.resolve_command(parent, ["train"])
    data = TrajectoryData.load(user_files["data"])
    resolved = {recipe: resolve_train_config(TrainConfig(dataset=user_files["data"], model=model,
                                                         recipe=recipe), data).model_options
                for recipe in ("mpnode", "paper")}
    checked = 0
    for option in command.params:
        found = re.search(rf"\b{model} \(([^;)]+)(?:; paper recipe ([^)]+))?\)", option.help or "")
        if option.name not in resolved["mpnode"] or not found:
            continue
        ours, paper = found.group(1), found.group(2) or found.group(1)
        for recipe, said in (("mpnode", ours), ("paper", paper)):
            value = resolved[recipe][option.name]
            assert said == (("on" if value else "off") if isinstance(value, bool)
                            else f"{value:g}" if isinstance(value, float) else str(value)), (
                option.name, recipe)
        checked += 1
    assert checked >= (6 if model == "mpnode" else 3)
