"""The `mpnode` command: a typer root that imports each verb's heavy modules lazily.

`mpnode --help` must stay instant, so nothing at module level here imports torch, h5py or
matplotlib; each command function imports what it needs when it runs.
"""

from __future__ import annotations

import typer

from mpnode_cli import __version__
from mpnode_cli.cli.generate import generate_command
from mpnode_cli.cli.info import info_command

app = typer.Typer(
    name="mpnode",
    help=(
        "Learn modular simulations of networked dynamical systems with message-passing "
        "neural ODEs (MP-NODE): generate ground truth on graphs, train one node network, "
        "and reuse it on graphs of other sizes and shapes."
    ),
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"mpnode {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Show the version."
    ),
) -> None:
    """mpnode: message-passing neural ODEs for homogeneous networked systems."""


def _not_implemented(verb: str) -> None:
    typer.echo(f"mpnode {verb}: not implemented yet", err=True)
    raise typer.Exit(code=2)


# Each verb's module imports only typer at load time; heavy imports live in its function.
app.command("generate", no_args_is_help=True)(generate_command)
app.command("info")(info_command)

# Verbs whose issues have not landed yet: they say so and exit 2 rather than pretend.
for _verb, _help in [
    ("train", "Train a model on a dataset."),
    ("finetune", "Continue training a checkpoint on another dataset."),
    ("evaluate", "Roll out a checkpoint on a dataset and report errors."),
    ("zeroshot", "Evaluate a checkpoint on graphs it never saw."),
    ("compare", "Compare training runs side by side."),
]:

    def _placeholder(
        args: list[str] | None = typer.Argument(None, hidden=True), _verb: str = _verb
    ) -> None:
        _not_implemented(_verb)

    app.command(
        _verb,
        help=f"{_help} (not implemented yet)",
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
    )(_placeholder)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
