"""What every verb shares: options declared elsewhere (threads, the solver's), and turning
exceptions into one line for the user and an exit code."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import typer
from pydantic import BaseModel

from mpnode_cli.solver.options import SolverOptions

T = TypeVar("T")
M = TypeVar("M", bound=BaseModel)

# Jobs whose memory estimate passes these sizes get the estimate printed, and a question
# (`confirm_size`: generate and simulate); so does the estimate of a job this slow.
SHOW_BYTES = 256 * 2**20
CONFIRM_BYTES = 4 * 2**30
SHOW_SECONDS = 5.0

# Every computing verb's `--threads` (the root's `mpnode --threads N VERB` works too; the
# verb's wins). `cli/app.py` reads and applies it before the verb runs; the verb ignores it.
THREADS = typer.Option(
    None, "--threads", metavar="N", show_default=False,
    help="CPU threads torch may use (default 1, or MPNODE_THREADS).")

# The switches of the verbs that write one output file (generate, import, merge, simulate),
# that may ask before a big job (generate, simulate), and that summarize as JSON.
FORCE = typer.Option(
    False, "--force", help="Overwrite an existing output file (regular files only).")
YES = typer.Option(False, "--yes", "-y", help="Go ahead with a big job without asking.")
JSON_OUT = typer.Option(
    False, "--json", help="Print the summary as one JSON object on stdout.")

# `--member K` of the verbs that roll a checkpoint out (evaluate, zeroshot, simulate).
MEMBER = typer.Option(
    None, "--member", metavar="K", show_default=False,
    help="Use member K (0, 1, ..) of an ensemble checkpoint (train --seeds) alone, not the "
    "members' mean.")


def solver_option(name: str, defaults: SolverOptions) -> Any:
    """The CLI option of one `SolverOptions` field: its declared help and the verb's default.

    Options left out stay out (None), so that the config fills them from its own defaults.

    Args:
        name: the field (`method`, `rtol`, `atol`, `fixed_dt`).
        defaults: the verb's options (`config.generate_solver()`, `config.train_solver()`).
    """
    value = getattr(defaults, name)
    shown = "" if value is None else f" (default {_number(value)})"
    text = SolverOptions.model_fields[name].description or name
    return typer.Option(None, help=f"{text.removesuffix('.')}{shown}.")


def _number(value: Any) -> str:
    """`1e-4` rather than `0.0001` for small and large floats; other values as they are."""
    if not isinstance(value, float) or value == 0 or 1e-3 <= abs(value) < 1e4:
        return f"{value:g}" if isinstance(value, float) else str(value)
    mantissa, exponent = f"{value:.12e}".split("e")
    return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"


def error_message(exc: Exception) -> str:
    """One line for a user: pydantic's multi-line errors condensed, others as they are."""
    from pydantic import ValidationError

    from mpnode_cli.config.file import error_line

    return error_line(exc) if isinstance(exc, ValidationError) else str(exc)


def config_from(config: type[M], options: dict[str, Any]) -> M:
    """A verb's `config` from its parameters (`options`: the command's `locals()`, taken
    before any other local name): those the config declares, where given (None is left
    out, for the config's default). A refused value is one `Error:` line (exit 2)."""
    try:
        return config(**{k: v for k, v in options.items()
                         if k in config.model_fields and v is not None})
    except ValueError as exc:
        fail(error_message(exc))


def fail(message: str, code: int = 2) -> None:
    """Print `Error: message` to stderr and exit (2: usage, 1: numerical failure)."""
    if speaks():
        typer.echo(f"Error: {message}", err=True)
    raise typer.Exit(code=code)


def warn(message: str) -> None:
    """Print `Warning: message` to stderr: something the user should know, not an error."""
    if speaks():
        typer.echo(f"Warning: {message}", err=True)


def extrapolation_note(row: dict[str, Any], name: str | None = None) -> None:
    """`warn` of a result's `extrapolation` note (evaluate, zeroshot, simulate), if it has
    one; `name` (the target's) leads the line where several targets are reported."""
    note = (row.get("extrapolation") or {}).get("note")
    if note:
        warn(f"{name}: {note}" if name else note)


def confirm_size(size: Any, job: str, yes: bool) -> None:
    """Print the estimate of a big or slow job; above `CONFIRM_BYTES` ask (or refuse
    without a terminal).

    Args:
        size: the job's `mpnode_cli.data.size.SizeEstimate`.
        job: what it makes, "K trajectories × T samples × N nodes".
        yes: go ahead without asking (`--yes`).

    Raises:
        ValueError: the user said no, or could not be asked and did not pass --yes.
    """
    import sys

    from mpnode_cli.memory import format_bytes

    if size.memory_bytes < SHOW_BYTES and (size.seconds or 0) < SHOW_SECONDS:
        return
    typer.echo(f"this job: {job}; {size.describe()}", err=True)
    if size.memory_bytes < CONFIRM_BYTES or yes:
        return
    if not sys.stdin.isatty():
        raise ValueError(f"a job this big (about {format_bytes(size.memory_bytes)} of memory) "
                         "needs confirmation: pass --yes to go ahead")
    if not typer.confirm("Go ahead?", default=False, err=True):
        raise ValueError("not confirmed; nothing done")


def speaks() -> bool:
    """False in the processes other than rank 0 that torchrun starts (its RANK variable):
    they exit as rank 0 does, but only rank 0 prints."""
    import os

    return os.environ.get("RANK", "0") in ("", "0")


def console(stderr: bool = False):
    """A rich console. Written to a pipe or a file, its lines are never wrapped (rich would
    break them at 80 columns, and a path or a suggested command in two is useless to
    copy); tables fit `mpnode_cli.report.tables.PIPE_WIDTH` columns there all the same.
    On a stream that cannot encode mpnode's characters (`ascii_fallback`), rich draws
    its tables with ASCII."""
    from rich.console import Console

    ascii_fallback()
    probe = Console(stderr=stderr)
    return probe if probe.is_terminal else Console(stderr=stderr, width=_UNWRAPPED)


def ascii_fallback() -> None:
    """Make stdout and stderr survive any terminal: where one cannot encode the characters
    mpnode prints (×, —, ≥, ... under `LC_ALL=C PYTHONIOENCODING=ascii`), it writes them
    as ASCII (`x`, `--`, `>=`; `?` for any other) instead of raising UnicodeEncodeError.
    The one place that decides; called before a verb prints (`mpnode_cli.cli.app`)."""
    import sys

    from mpnode_cli.terminal import ASCII_ERRORS, register_ascii_errors

    register_ascii_errors()
    for stream in (sys.stdout, sys.stderr):
        encoding = getattr(stream, "encoding", None) or "utf-8"
        try:
            _SAMPLE.encode(encoding)
        except UnicodeEncodeError:
            if hasattr(stream, "reconfigure"):
                stream.reconfigure(errors=ASCII_ERRORS)
        except LookupError:  # an encoding Python does not know: leave the stream alone
            pass


# Characters mpnode prints that a stream must encode to be left as it is.
_SAMPLE = "×—…≥±→"


def output_parser(option: str, *, folder: bool = False) -> Callable[[Any], Any]:
    """The `parser` of an output path option (`typer.Option(..., parser=...)`): the path as
    typed, refused in one line (exit 2) when empty or, for a file, ending in `/`
    (`mpnode_cli.paths.output_arg`), before typer turns it into a `Path` (which drops the
    slash).

    Args:
        option: the option's name, for the message (`--out`).
        folder: whether it names a folder.
    """

    def parse(text: Any) -> Any:
        from mpnode_cli.paths import output_arg

        try:
            return output_arg(text, option, folder=folder)
        except ValueError as exc:
            fail(str(exc))

    return parse


# Columns of a console that is not a terminal: wider than any line mpnode prints.
_UNWRAPPED = 100_000


def split_by_name(counts) -> dict[str, int]:
    """Trajectories per split as every verb's `--json` reports them (key "split"):
    `{"train": ..., "validation": ..., "test": ...}` from the three counts."""
    from mpnode_cli.data.hdf5 import SPLIT_NAMES

    return {name: int(count) for name, count in zip(SPLIT_NAMES, counts, strict=True)}


@contextmanager
def task_bar(description: str, columns: tuple | None = None, total: float | None = None, *,
             quiet: bool = False) -> Iterator[tuple]:
    """A transient rich progress bar on stderr, and the `progress(done, total)` callback
    that moves it (None leaves a count as it is; a third argument, `description`, says what
    is being done now): `(bar, progress)`. The bar appears at the first call of `progress`,
    so what the work prints or asks before it starts (`confirm_size`) is not under a live
    display. No bar when stderr is not a terminal (pipes, logs, tests), nor when `quiet`
    (`--json`): it would only add noise.

    Args:
        description: what is being done.
        columns: rich's progress columns (default: the description, a bar, the percentage,
            the time elapsed and the time left).
        total: the work in all, if known before the first call.
        quiet: no bar, even on a terminal.
    """
    from rich.progress import BarColumn, Progress, TimeElapsedColumn, TimeRemainingColumn

    display = console(stderr=True)
    columns = columns or ("[progress.description]{task.description}", BarColumn(),
                          "[progress.percentage]{task.percentage:>3.0f}%",
                          TimeElapsedColumn(), TimeRemainingColumn())
    bar = Progress(*columns, console=display, transient=True,
                   disable=quiet or not display.is_terminal)
    task = bar.add_task(description, total=total)

    def progress(done: float | None, total: float | None, description: str | None = None
                 ) -> None:
        if not bar.live.is_started:
            bar.start()
        bar.update(task, completed=done, total=total, description=description)

    try:
        yield bar, progress
    finally:
        if bar.live.is_started:
            bar.stop()


def with_bar(description: str, work: Callable[[Callable], T], *, quiet: bool, stopped: str,
             failures: tuple[type[Exception], ...] = (), columns: tuple | None = None,
             total: float | None = None) -> T:
    """`work(progress)` behind a `task_bar`, SIGTERM taken as Ctrl-C, and what it raises
    turned into one line and an exit code: 2 for what the user can fix (a `ValueError`, a
    missing or existing file), 1 for `failures` (numbers that did not work out), 130 / 143
    for an interrupt ("Interrupted (SIGINT): <stopped>").

    Args:
        description, columns, total: the bar's (`task_bar`).
        work: the library call, given the bar's `progress(done, total)` callback.
        quiet: no bar (`--json`).
        stopped: what an interrupt left, e.g. "nothing written".
        failures: exception types that mean a numerical failure (exit 1).
    """
    from mpnode_cli.signals import exit_code, interrupt_on_signals, signal_name

    try:  # the bar is gone before a message is printed
        with interrupt_on_signals(), task_bar(description, columns, total, quiet=quiet
                                              ) as (_, progress):
            return work(progress)
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        fail(error_message(exc))
    except failures as exc:
        fail(str(exc), code=1)
    except MemoryError as exc:  # numpy's _ArrayMemoryError too; the writes left nothing
        fail(out_of_memory(exc, description))
    except KeyboardInterrupt as exc:
        typer.echo(f"Interrupted ({signal_name(exc)}): {stopped}", err=True)
        raise typer.Exit(code=exit_code(exc)) from None


def out_of_memory(exc: MemoryError, doing: str) -> str:
    """One line for a `MemoryError`: the step that ran out (`doing`, or the step the error
    names itself, as `mpnode_cli.training.predict` does), what numpy could not allocate,
    and that nothing was written."""
    said = str(exc).strip()
    step = said if said.startswith("out of memory") else f"out of memory while {doing}"
    detail = "" if said.startswith("out of memory") or not said else f" ({said})"
    return (f"{step}{detail}; nothing was written: use a smaller job (fewer trajectories or "
            "samples), or a machine with more memory")


def hide_flag_types() -> None:
    """Show no type beside a flag in help: typer labels every flag `<bool>`, which reads
    as if it took a value."""
    from typer.core import TyperOption

    shown = TyperOption.display_type_rich
    if getattr(shown, "_mpnode", False):
        return

    def display_type_rich(self, ctx):
        return None if self.is_flag else shown(self, ctx)

    display_type_rich._mpnode = True  # type: ignore[attr-defined]
    TyperOption.display_type_rich = display_type_rich  # type: ignore[method-assign]
