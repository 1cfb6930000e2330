"""`mpnode experiment list` and `mpnode experiment run NAME`: the paper's experiments, one
command each.

`run` executes the experiment's steps through the library (`mpnode_cli.experiments.runner`),
skipping those finished by an earlier run, and writes `reports/<name>/report.md` and the
index `reports/README.md`. Exit codes: 2 for usage errors (unknown experiment, scale or
recipe), 1 when a step fails, 130 for Ctrl-C (finished steps are kept; the same command
resumes).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from mpnode_cli.cli.common import THREADS, console, error_message, fail, output_parser

experiment_app = typer.Typer(
    help="The paper's experiments, one command each, with reports beside the paper's numbers.",
    no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False)

_SCALES = ("tiny", "small", "paper")
_RECIPES = {"mpnode": "mpnode", "ours": "mpnode", "paper": "paper"}
# The largest data draw: its seeds (draw × spec.DRAW_STRIDE) stay far inside an int64.
_MAX_DRAW = 10**6


def _complete_name(incomplete: str) -> list[str]:
    from mpnode_cli.experiments.spec import names

    return [name for name in names() if name.startswith(incomplete)]


def list_command(
    scale: str = typer.Option(
        "small", help="small: the expected minutes at the small scale; paper: the estimated "
        "core-hours of training at the paper's scale, from the seconds per epoch measured "
        "in the experiment's committed runs (under --out)."),
    out: Path = typer.Option(Path("reports"), help="Where the runs' reports are (what "
                             "--scale paper reads its measurements from)."),
) -> None:
    """List the experiments: name, what of the paper it reproduces, steps, and the
    expected minutes at the small scale (one core; steps done earlier are skipped), or with
    `--scale paper` the estimated core-hours of their training at the paper's scale."""
    from mpnode_cli.experiments.spec import load, names
    from mpnode_cli.report.tables import titled

    if scale not in ("small", "paper"):
        fail(f"unknown scale '{scale}' (choose from: small, paper)")
    table = titled("mpnode experiment run NAME [--scale small|paper] [--recipe mpnode|paper] "
                   "[--seeds S]")
    last = "small, min" if scale == "small" else "paper, core-h"
    for column in ("name", "the paper", "title", "steps", last):
        table.add_column(column)
    estimates = {}
    for name in names():
        experiment = load(name)
        if scale == "paper":
            from mpnode_cli.experiments.estimate import paper_cost

            estimates[name] = paper_cost(experiment, out)
            cost = estimates[name].shown()
        else:
            minutes = experiment.small_minutes
            cost = "—" if minutes is None else f"~{minutes:g}"
        table.add_row(name, experiment.paper, experiment.title, str(len(experiment.steps)),
                      cost)
    console().print(table)
    if scale == "paper":
        _explain_paper_cost(estimates, out)


def _explain_paper_cost(estimates: dict[str, Any], out: Path) -> None:
    """How `--scale paper`'s column is estimated, and what it leaves out."""
    from mpnode_cli.experiments.estimate import HOW

    lines = [f"paper, core-h: {HOW}."]
    resized = sorted({s for e in estimates.values() for s in e.resized})
    if resized:
        lines.append("*: a step measured with a smaller model than the paper scale's (L2S "
                     f"runs CI-sized at the small scale: {', '.join(resized)}), so it costs "
                     "more than shown.")
    if any(e.missing for e in estimates.values()):
        lines.append("≥: some training steps have no measured run, and are left out; —: no "
                     f"run of the experiment under {out}.")
    for line in lines:
        typer.echo(line)


def report_command(
    names: list[str] | None = typer.Argument(
        None, metavar="NAME", show_default=False,
        help="Experiments whose reports to rebuild (default: every one with saved runs)."),
    out: Path = typer.Option(Path("reports"), help="Where the runs' records and reports "
                             "are (<out>/<name>/<scale>-<recipe>/results.json).",
                             parser=output_parser("--out", folder=True)),
) -> None:
    """Rebuild reports and the index from the saved runs' records alone, running nothing:
    every claim is judged anew from its experiment's spec."""
    from mpnode_cli.experiments.index import rebuild_index
    from mpnode_cli.experiments.report import rebuild_report
    from mpnode_cli.experiments.saved import saved_runs
    from mpnode_cli.experiments.spec import load
    from mpnode_cli.experiments.spec import names as shipped

    try:
        experiments = [load(name) for name in (names or shipped())]
        chosen = [e for e in experiments if names or saved_runs(out, e.name)]
        _check_reports(out, None, [])
        if not chosen:  # a mistyped --out: no index of runs that are not there
            raise ValueError(f"no saved runs under {out}: nothing to report (mpnode "
                             "experiment run writes them there)")
        for experiment in chosen:
            if not saved_runs(out, experiment.name):
                raise ValueError(f"no saved run of {experiment.name} under {out}")
            _check_reports(out, experiment.name, [])
            typer.echo(f"rebuilt {rebuild_report(experiment, out)}")
        typer.echo(f"rebuilt {rebuild_index(out)}")
    except (FileExistsError, ValueError) as exc:
        fail(error_message(exc))
    except OSError as exc:  # a record that cannot be read, a report the disk cannot take
        fail(f"cannot rebuild the reports in {out}: "
             f"{exc.filename or ''}{': ' * bool(exc.filename)}{exc.strerror or exc}")


def run_command(
    name: str = typer.Argument(..., help="An experiment (mpnode experiment list), or a .toml "
                               "file of one.", autocompletion=_complete_name,
                               show_default=False),
    scale: str = typer.Option(
        "small", help="small (18-136 minutes each on one core: experiment list), paper "
        "(the paper's sizes and epochs) or tiny (a smoke test: a few trajectories, two "
        "epochs)."),
    recipe: str = typer.Option(
        "mpnode", help="Training recipe: mpnode (default; alias ours) or paper."),
    out: Path = typer.Option(
        Path("reports"), help="Where reports go (<out>/<name>/report.md, and the index "
        "<out>/README.md: a README.md there that mpnode did not write is refused).",
        parser=output_parser("--out", folder=True)),
    work: Path = typer.Option(
        Path("runs/experiments"), help="Step folders (datasets, runs); finished steps found "
        "here are reused.", parser=output_parser("--work", folder=True)),
    jobs: int = typer.Option(
        1, "--jobs", "-j", metavar="N",
        help="Processes running steps side by side, each on --threads threads: a step "
        "runs once its inputs are done (2 on 2 cores takes about half the time)."),
    seeds: int = typer.Option(
        3, metavar="S",
        help="Train every model as an ensemble of S members in one run (member k with the "
        "step's seed + k); reports give each number as mean ± std over the members, and a "
        "claim holds, fails or is undecided from the members (docs/reproducing.md). 1: one "
        "model per training step."),
    draw: int = typer.Option(
        0, metavar="D",
        help="Data draw: every generated dataset's seed and graph seed offset by D × 1000 "
        "(other graphs, initial states, split, per-graph parameters such as Kuramoto's ω). "
        "0 is the experiment's own data; each draw's report section goes beside it, and "
        "with two or more draws every claim gets its margin and a 95% bootstrap interval "
        "over the draws and seeds."),
    threads: str | None = THREADS,
) -> None:
    """Run (or resume) an experiment and write its report."""
    import shlex

    from mpnode_cli.experiments.saved import run_folder, saved_runs
    from mpnode_cli.experiments.spec import load
    from mpnode_cli.paths import check_output_folder
    from mpnode_cli.threads import available_cpus

    if scale not in _SCALES:
        fail(f"unknown scale '{scale}' (choose from: {', '.join(_SCALES)})")
    if jobs < 1:
        fail(f"jobs: Input should be greater than or equal to 1 (got {jobs})")
    if seeds < 1:
        fail(f"seeds: Input should be greater than or equal to 1 (got {seeds})")
    if not 0 <= draw <= _MAX_DRAW:
        fail(f"draw: Input should be from 0 to {_MAX_DRAW} (got {draw})")
    if jobs > available_cpus():  # each job is a process holding torch: never one per typo
        fail(f"--jobs must be at most {available_cpus()}, the CPUs this process may use, "
             f"got {jobs}")
    if recipe not in _RECIPES:
        fail(f"unknown recipe '{recipe}' (choose from: mpnode (or ours), paper)")
    try:
        experiment = load(name)
        # Both folders are written: --work by every step, --out after the last.
        check_output_folder(work)
        check_output_folder(out / experiment.name)
        _check_reports(out, experiment.name, [run_folder(scale, _RECIPES[recipe], draw)])
        saved_runs(out, experiment.name)  # the records its report is rebuilt from: readable
    except (FileExistsError, ValueError) as exc:
        fail(error_message(exc))
    except OSError as exc:
        fail(f"cannot read {exc.filename or out}: {exc.strerror or exc}")
    command = shlex.join(["mpnode", "experiment", "run", name, "--scale", scale, "--recipe",
                          _RECIPES[recipe], "--seeds", str(seeds),
                          *(["--draw", str(draw)] if draw else []), *_given_paths(out, work),
                          *(["--jobs", str(jobs)] if jobs > 1 else [])])
    _run(experiment, scale, _RECIPES[recipe], out, work, command, jobs, seeds, draw)


def _check_reports(out: Path, name: str | None, runs: list[str]) -> None:
    """The files `write_report` rewrites (`<out>/README.md`, `<out>/<name>/report.md`) and
    the folders it replaces (`<out>/<name>/<scale>-<recipe>/`, `runs`) may be there only as
    mpnode wrote them: a user's own README.md or folder is never replaced. With `name`
    None, the index only.

    Raises:
        FileExistsError, ValueError: one line (`mpnode_cli.paths.check_output_file`).
    """
    from mpnode_cli.experiments.saved import INDEX, INDEX_TITLE, REPORT, RESULTS
    from mpnode_cli.paths import check_output_file

    check_output_file(out / INDEX, overwrite=False, mine=INDEX_TITLE.encode())
    if name is None:  # the index only
        return
    check_output_file(out / name / REPORT, overwrite=False, mine=f"# {name}: ".encode())
    for run in runs:
        folder = out / name / run
        if folder.exists() and not (folder / RESULTS).is_file():
            raise FileExistsError(f"{folder} exists and holds no {RESULTS} of an mpnode "
                                  "report: move it away or choose another --out")


def _given_paths(out: Path, work: Path) -> list[str]:
    """`--out`/`--work` for the recorded command, when not the defaults: relative to the
    current folder, or `<out>`/`<work>` for a folder outside it (reports are committed,
    and the folders of the machine that ran them mean nothing elsewhere)."""
    from mpnode_cli.file_records import shown_path

    extra = []
    if out != Path("reports"):
        extra += ["--out", shown_path(out, "<out>")]
    if work != Path("runs/experiments"):
        extra += ["--work", shown_path(work, "<work>")]
    return extra


def _run(experiment, scale: str, recipe: str, out: Path, work: Path, command: str,
         jobs: int = 1, seeds: int = 1, draw: int = 0) -> None:
    from mpnode_cli.experiments.report import write_report
    from mpnode_cli.experiments.runner import StepFailed, run_experiment
    from mpnode_cli.signals import exit_code, interrupt_on_signals, signal_name
    from mpnode_cli.training.loop import TrainingInterrupted

    display = _Steps(console(stderr=True))
    try:
        with interrupt_on_signals():
            record = run_experiment(experiment, scale=scale, recipe=recipe, work=work,
                                    command=command, progress=display.on_event, jobs=jobs,
                                    seeds=seeds, draw=draw)
    except StepFailed as exc:
        display.close()
        fail(str(exc), code=1)
    except ValueError as exc:  # a work folder or --seeds that cannot be used (before any step)
        display.close()
        fail(error_message(exc))
    except (TrainingInterrupted, KeyboardInterrupt) as exc:
        display.close()
        cause = exc.cause if isinstance(exc, TrainingInterrupted) else exc
        typer.echo(f"Interrupted ({signal_name(cause)}): finished steps are kept in {work}, "
                   f"and an interrupted training continues from its last epoch; run the "
                   f"same command again to resume", err=True)
        raise typer.Exit(code=exit_code(cause)) from None
    try:
        path = write_report(record, experiment, out)
    except (OSError, ValueError) as exc:  # checked first, but the disk may fill, a folder go
        said = getattr(exc, "strerror", None) or exc
        fail(f"cannot write the report in {out}: {said} (the steps are done "
             f"and kept in {work}: run the same command again to write it)")
    ran = sum(step.status != "skipped" for step in record.steps)
    typer.echo(f"{experiment.name}: {ran} of {len(record.steps)} steps ran, "
               f"{record.wall_seconds / 60:.1f} min; wrote {path} and {out / 'README.md'}")


class _Steps:
    """A line per step, and the verb's own progress display while it runs."""

    def __init__(self, out):
        self.console = out
        self.inner: Any = None

    def close(self) -> None:
        if self.inner is not None:
            self.inner.__exit__(None, None, None)
            self.inner = None

    def on_event(self, event: dict[str, Any]) -> None:
        kind = event["event"]
        if kind == "step" and event.get("worker"):
            self.console.print(f"[bold][{event['index']}/{event['total']}] {event['verb']} "
                               f"{event['id']}[/bold]: ran in a worker process "
                               f"({event['folder']})")
        elif kind == "step":
            verb = {"skipped": "done earlier, skipped", "resumed": "resuming",
                    "ran": "running"}[event["status"]]
            self.console.print(f"[bold][{event['index']}/{event['total']}] {event['verb']} "
                               f"{event['id']}[/bold]: {verb} ({event['folder']})")
            if event["status"] != "skipped" and event["verb"] in ("train", "finetune"):
                from mpnode_cli.cli.train_display import TrainingDisplay

                self.inner = TrainingDisplay(self.console).__enter__()
            elif event["status"] != "skipped" and event["verb"] == "generate":
                self.inner = _GenerateBar(self.console).__enter__()
        elif kind == "train" and self.inner is not None:
            self.inner.on_event(event["event_data"])
        elif kind == "generate" and self.inner is not None:
            self.inner.update(event["done"], event["total"])
        elif kind == "waiting":
            self.console.print(f"    step {event['id']} is being run by another process "
                               f"(lock {event['lock']}); waiting for it")
        elif kind == "step-done":
            self.close()
            if event["status"] != "skipped":
                self.console.print(f"    {event['seconds']:.1f} s: {event['line']}")


class _GenerateBar:
    """`mpnode generate`'s progress bar (none when stderr is not a terminal)."""

    def __init__(self, out):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

        self.bar = Progress("[progress.description]{task.description}", BarColumn(),
                            MofNCompleteColumn(), TimeElapsedColumn(), console=out,
                            transient=True, disable=not out.is_terminal)
        self.task = self.bar.add_task("solving", total=None)

    def __enter__(self):
        self.bar.__enter__()
        return self

    def __exit__(self, *exc):
        return self.bar.__exit__(*exc)

    def update(self, done: int, total: int) -> None:
        self.bar.update(self.task, completed=done, total=total)
