"""The `mpnode` command lines the reports give for each step (`experiments.commands`) parse
with the real typer app: every option they name exists and takes the value given."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import typer

from mpnode_cli import flags
from mpnode_cli.cli.app import app
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
            lines.append(commands.generate(step, options, Path("data.h5")))
        elif step.verb in spec.TRAINING:
            checkpoint = Path("parent/best.pt") if step.verb == "finetune" else None
            lines.append(commands.train(step, options, Path("data.h5"), Path("run"),
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
    from mpnode_cli.config import TrainConfig

    booleans = [n for n, f in TrainConfig.model_fields.items() if f.annotation is bool]
    assert "even_batches" in booleans and "renormalize" in booleans
    for name in booleans:
        head = "mpnode finetune parent.pt data.h5" if name in (
            "renormalize", "allow_other_system") else "mpnode train data.h5"
        parses(" ".join([head, *flags.words(name, value)]))
