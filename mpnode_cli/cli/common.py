"""What every verb shares: turning exceptions into one line for the user and an exit code."""

from __future__ import annotations

import typer

# Every computing verb's `--threads` (the root's `mpnode --threads N VERB` works too; the
# verb's wins). `cli/app.py` reads and applies it before the verb runs; the verb ignores it.
THREADS = typer.Option(
    None, "--threads", metavar="N", show_default=False,
    help="CPU threads torch may use (default 1, or MPNODE_THREADS).")


def error_message(exc: Exception) -> str:
    """One line for a user: pydantic's multi-line errors condensed, others as they are."""
    from pydantic import ValidationError

    from mpnode_cli.config import error_line

    return error_line(exc) if isinstance(exc, ValidationError) else str(exc)


def fail(message: str, code: int = 2) -> None:
    """Print `Error: message` to stderr and exit (2: usage, 1: numerical failure)."""
    typer.echo(f"Error: {message}", err=True)
    raise typer.Exit(code=code)


def console(stderr: bool = False):
    """A rich console; tables written to a pipe or file get 120 columns, not rich's 80."""
    from rich.console import Console

    probe = Console(stderr=stderr)
    return probe if probe.is_terminal else Console(stderr=stderr, width=120)
