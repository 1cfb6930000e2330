"""The `mpnode` command: a typer root that imports each verb's heavy modules lazily.

`mpnode --help` must stay instant, so nothing at module level here imports torch, h5py or
matplotlib; each command function imports what it needs when it runs.
"""

from __future__ import annotations

import typer

from mpnode_cli import __version__
from mpnode_cli.cli.evaluate import compare_command, evaluate_command, zeroshot_command
from mpnode_cli.cli.generate import generate_command
from mpnode_cli.cli.info import info_command
from mpnode_cli.cli.train import finetune_command, train_command

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


# Each verb's module imports only typer at load time; heavy imports live in its function.
app.command("generate", no_args_is_help=True)(generate_command)
app.command("info")(info_command)
app.command("train")(train_command)
app.command("finetune", no_args_is_help=True)(finetune_command)
app.command("evaluate", no_args_is_help=True)(evaluate_command)
app.command("zeroshot", no_args_is_help=True)(zeroshot_command)
app.command("compare", no_args_is_help=True)(compare_command)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
