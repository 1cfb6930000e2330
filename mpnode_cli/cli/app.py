"""The `mpnode` command: a typer root that imports each verb's heavy modules lazily.

`mpnode --help` must stay instant, so nothing at module level here imports torch, h5py or
matplotlib; each command function imports what it needs when it runs.

Thread count is a property of the process: a root option (`mpnode --threads N VERB ...`),
the same option on every computing verb (`mpnode VERB ... --threads N`, which wins) and
`MPNODE_THREADS`. Each computing verb decides and applies it (a bad value is a one-line
usage error) after parsing its options, before it runs.
"""

from __future__ import annotations

import errno
from typing import Any

import typer
from typer.core import TyperCommand

from mpnode_cli import __version__
from mpnode_cli.cli.check import check_command
from mpnode_cli.cli.common import ascii_fallback, fail, hide_flag_types
from mpnode_cli.cli.evaluate import compare_command, evaluate_command, zeroshot_command
from mpnode_cli.cli.experiment import (
    experiment_app,
    list_command,
    report_command,
    run_command,
)
from mpnode_cli.cli.generate import generate_command
from mpnode_cli.cli.importer import import_command
from mpnode_cli.cli.info import info_command
from mpnode_cli.cli.merge import merge_command
from mpnode_cli.cli.simulate import simulate_command
from mpnode_cli.cli.train import finetune_command, train_command
from mpnode_cli.threads import ENV_VAR, apply_threads, choose_threads

app = typer.Typer(
    name="mpnode",
    help=(
        "Learn modular simulations of networked dynamical systems with message-passing "
        "neural ODEs (MP-NODE): generate ground truth on graphs, train one node network, "
        "and reuse it on graphs of other sizes and shapes."
    ),
    no_args_is_help=True,
    add_completion=True,
    pretty_exceptions_enable=False,
)
hide_flag_types()
_THREADS = "mpnode.threads"  # where the root leaves `--threads` for the verb in click's context


def _version_callback(value: bool) -> None:
    if value:
        typer.echo(f"mpnode {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    ctx: typer.Context,
    version: bool = typer.Option(
        False, "--version", callback=_version_callback, is_eager=True, help="Show the version."
    ),
    threads: str | None = typer.Option(
        None, "--threads", metavar="N", show_default=False,
        help=f"CPU threads torch may use (default 1; or set {ENV_VAR}).",
    ),
) -> None:
    """mpnode: message-passing neural ODEs for homogeneous networked systems."""
    ascii_fallback()  # before any verb prints (`main` did it for help and usage errors)
    ctx.meta[_THREADS] = threads


class _Computing(TyperCommand):
    """A verb that runs torch: its thread pools are sized once its options have parsed (so
    `VERB --help` imports no torch, whatever the setting) and before its function runs."""

    def invoke(self, ctx: typer.Context) -> Any:
        try:
            own = ctx.params.get("threads")
            choice = choose_threads(own if own is not None else ctx.meta.get(_THREADS))
        except ValueError as exc:
            fail(str(exc))
        apply_threads(choice)
        return _disk_full_is_one_line(super().invoke, ctx)


class _Threadless(TyperCommand):
    """A verb that sizes no thread pools: the root's `--threads` and `MPNODE_THREADS` are
    still checked once its options have parsed (`VERB --help` wins), as a computing verb
    checks them, so that a slip is one line and not silently ignored."""

    def invoke(self, ctx: typer.Context) -> Any:
        try:
            choose_threads(ctx.meta.get(_THREADS))
        except ValueError as exc:
            fail(str(exc))
        return _disk_full_is_one_line(super().invoke, ctx)


def _disk_full_is_one_line(invoke: Any, ctx: typer.Context) -> Any:
    """Run a verb; a full disk that a write of its own meets in a file it names (a folder,
    a metrics row; the atomic writes say it themselves) is one line and exit 2 too, and so
    is a disk that fails a read or a write (EIO), wherever it is met (exit 1)."""
    import errno

    try:
        return invoke(ctx)
    except OSError as exc:
        if exc.errno == errno.EIO and (exc.filename is not None or _stdout_writes()):
            where = f" on {exc.filename}" if exc.filename is not None else ""
            fail(f"input/output error{where} (errno 5: the disk or the device behind it "
                 "failed a read or a write); check it and run the command again", code=1)
        if exc.filename is None or exc.errno not in (errno.ENOSPC, errno.EDQUOT):
            raise  # stdout's own (`main`), or not a full disk
        fail(f"no space left on device writing {exc.filename}: free some space and run it "
             "again")


def _stdout_writes() -> bool:
    """Whether standard output still takes writes (its buffered part flushed): an error
    without a file name is then a file's, not stdout's (which `main` says)."""
    import sys

    try:
        if sys.stdout is not None:
            sys.stdout.flush()
    except OSError:
        return False
    return True


# Each verb's module imports only typer at load time; heavy imports live in its function.
# compare only reads JSON, so it has no threads to size.
app.command("generate", no_args_is_help=True, cls=_Computing)(generate_command)
app.command("merge", no_args_is_help=True, cls=_Threadless)(merge_command)
app.command("import", no_args_is_help=True, cls=_Threadless)(import_command)
app.command("info", cls=_Threadless)(info_command)
app.command("check", no_args_is_help=True, cls=_Threadless)(check_command)
app.command("train", cls=_Computing)(train_command)
app.command("finetune", no_args_is_help=True, cls=_Computing)(finetune_command)
app.command("evaluate", no_args_is_help=True, cls=_Computing)(evaluate_command)
app.command("zeroshot", no_args_is_help=True, cls=_Computing)(zeroshot_command)
app.command("simulate", no_args_is_help=True, cls=_Computing)(simulate_command)
app.command("compare", no_args_is_help=True, cls=_Threadless)(compare_command)
experiment_app.command("list")(list_command)
experiment_app.command("run", no_args_is_help=True, cls=_Computing)(run_command)
experiment_app.command("report", cls=_Threadless)(report_command)
app.add_typer(experiment_app, name="experiment")


def main() -> None:
    """`mpnode`: the app, and a stdout that cannot take its output (a full disk, a closed
    pipe) said in one line (exit 2; quietly, exit 1, for a pipe whose reader is gone, as
    click does inside a verb) rather than in a traceback."""
    import os
    import sys

    ascii_fallback()
    try:  # torch's loader would fail on it, naming a library (Intel oneMKL) instead
        os.getcwd()
    except FileNotFoundError:
        sys.stderr.write("Error: the current folder no longer exists (it was deleted or "
                         "moved): change to another folder and run it again\n")
        raise SystemExit(2) from None
    try:
        try:
            app(prog_name="mpnode")
        finally:
            if sys.stdout is not None:  # None: started with stdout closed
                sys.stdout.flush()  # what is left fails here, not untold at exit
    except OSError as exc:  # not a file of a verb's: those are checked, and said in one line
        if exc.filename is not None or exc.errno not in _UNWRITABLE:
            raise
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing left to fail
        if exc.errno == errno.EPIPE:
            raise SystemExit(1) from None
        sys.stderr.write(f"Error: cannot write to standard output: {exc.strerror}\n")
        raise SystemExit(2) from None


# What a write to stdout fails with when the output cannot take it.
_UNWRITABLE = {getattr(errno, name) for name in ("EPIPE", "ENOSPC", "EDQUOT", "EFBIG", "EIO")
               if hasattr(errno, name)}


if __name__ == "__main__":
    main()
