"""`mpnode evaluate`, `mpnode zeroshot` and `mpnode compare`: what a trained model is worth.

evaluate: one checkpoint on one dataset split, with optional plots. zeroshot: one checkpoint
on datasets of other sizes and topologies, with the training normalization and no training.
compare: runs side by side from their `summary.json` (or, unfinished, their metrics).
Every MSE is shown beside two naive predictors (hold x(0) and the train split's time mean;
`mpnode_cli.training.evaluate.baseline_mse`). An ensemble checkpoint (`train --seeds S`) is
scored on its members' mean, with the members' MSE as mean ± std, their spread and how
well the spread ranks the error; `--member K` scores one member alone.
Exit code 2 for anything the user can fix (a missing or invalid file, incompatible sizes,
another system's data without `--allow-other-system`, an unwritable plot folder).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

from mpnode_cli.cli.common import (
    MEMBER,
    THREADS,
    console,
    error_message,
    extrapolation_note,
    fail,
    output_parser,
)

_SPLITS = "train, validation, test or all"
_CHECKPOINT = typer.Argument(..., help="A checkpoint (.pt), or a run folder (its best.pt).")
_OTHER_SYSTEM = typer.Option(
    False, "--allow-other-system",
    help="Accept datasets of another system than the checkpoint was trained on.")
_TABLE_JSON = typer.Option(False, "--json", help="Print JSON instead of a table.")
_BATCH = typer.Option(128, help="Trajectories per rollout.")
_DEVICE = typer.Option("cpu", help="cpu or cuda.")


def _split(default: str) -> Any:
    return typer.Option(default, help=f"Which trajectories: {_SPLITS}.")


def evaluate_command(
    checkpoint: Path = _CHECKPOINT,
    dataset: Path = typer.Argument(..., help="An mpnode dataset (.h5)."),
    split: str = _split("test"),
    plot: bool = typer.Option(False, "--plot", help="Draw the Fig. 2 rollout and error plots."),
    plot_dir: Path | None = typer.Option(
        None, help="Where plots go (default <run>/plots beside the checkpoint, where the "
        "run's own plots are drawn again).",
        parser=output_parser("--plot-dir", folder=True)),
    json_out: bool = _TABLE_JSON,
    batch_size: int = _BATCH,
    device: str = _DEVICE,
    allow_other_system: bool = _OTHER_SYSTEM,
    save_predictions: Path | None = typer.Option(
        None, metavar="FILE", help="Write the split's predictions (physical units, messages "
        "under hidden/messages) as an mpnode dataset file (a file's path: not one ending in "
        "/).", parser=output_parser("--save-predictions")),
    force: bool = typer.Option(
        False, "--force", help="Overwrite existing output files: --save-predictions, and "
        "the --plot files (regular files only)."),
    member: int | None = MEMBER,
    threads: str | None = THREADS,
    by_degree: bool = typer.Option(
        False, "--by-degree", help="Also the errors by in-degree bin ([0,1), [1,2), [2,4), "
        "...; physical units) beside the naive predictors'."),
) -> None:
    """Roll out a checkpoint on a dataset split and report its errors."""
    from contextlib import ExitStack

    from mpnode_cli.paths import check_output_folder, reserve_output
    from mpnode_cli.report.tables import baselines_note, degree_table, metrics_table
    from mpnode_cli.training.checkpoint_report import plot_paths

    _check_batch_size(batch_size)
    ckpt = _load_checkpoint(checkpoint, member)
    checkpoint = ckpt.path or checkpoint
    where = (plot_dir or _default_plot_dir(checkpoint)) if plot else None
    if where is not None:
        try:
            check_output_folder(where)
        except ValueError as exc:
            fail(f"--plot-dir: {exc}")
    outputs = [("--plot", path) for path in (plot_paths(where, dataset, split) if where else ())]
    outputs += [("--save-predictions", save_predictions)] if save_predictions else []
    with ExitStack() as reserved:  # each file replaces its reservation: written with overwrite
        for option, path in outputs:  # every one checked before any work
            # The run folder's own plots (no --plot-dir) are mpnode's, drawn again.
            mine = option == "--plot" and plot_dir is None
            try:
                reserved.enter_context(reserve_output(path, overwrite=force or mine,
                                                      inputs=(checkpoint, dataset)))
            except (FileExistsError, ValueError) as exc:
                fail(f"{option}: {exc}")
        row = _evaluate(ckpt, dataset, split, "evaluate", batch_size, device, where,
                        allow_other_system, save_predictions, force=True, quiet=json_out,
                        by_degree=by_degree)
    if json_out:
        typer.echo(json.dumps({"checkpoint": str(checkpoint), **_member(member), **row},
                              indent=2))
        return
    title = f"{_named(checkpoint, member)} on {dataset} ({split}, N={row['num_nodes']})"
    console().print(metrics_table(row["result"], ckpt.dataset["state_names"], title,
                                  row["baselines"]))
    console().print(baselines_note(row["baselines_note"]))
    if row["data_note"]:
        console().print(f"note: {row['data_note']}", highlight=False)
    extrapolation_note(row)
    extrapolated_nodes(row)
    for path in [*row["plots"], *([row["predictions"]] if row["predictions"] else [])]:
        typer.echo(f"wrote {path}")
    if by_degree:
        console().print(degree_table(row["by_degree"], f"by in-degree: {_degree_caption(row)}"))


def zeroshot_command(
    checkpoint: Path = _CHECKPOINT,
    datasets: list[Path] = typer.Argument(..., help="Datasets of unseen graphs (.h5)."),
    split: str = _split("all"),
    json_out: bool = _TABLE_JSON,
    batch_size: int = _BATCH,
    device: str = _DEVICE,
    allow_other_system: bool = _OTHER_SYSTEM,
    member: int | None = MEMBER,
    threads: str | None = THREADS,
) -> None:
    """Run a trained node network on graphs it never saw, without training."""
    from mpnode_cli.report.tables import baselines_note, zeroshot_table

    _check_batch_size(batch_size)
    ckpt = _load_checkpoint(checkpoint, member)
    rows = [_evaluate(ckpt, path, split, "zeroshot", batch_size, device, None,
                      allow_other_system, quiet=json_out) for path in datasets]
    if json_out:
        typer.echo(json.dumps({"checkpoint": str(checkpoint), **_member(member),
                               "trained_on": ckpt.dataset, "datasets": rows}, indent=2))
        return
    trained = ckpt.dataset
    title = (f"zero-shot: {_named(checkpoint, member)} (trained on {trained['system']}, "
             f"N={trained['num_nodes']}, {trained.get('topology') or '?'})")
    console().print(zeroshot_table(
        [{**row, "dataset": Path(row["dataset"]).name} for row in rows], title))
    for note in dict.fromkeys(row["baselines_note"] for row in rows):  # unique, in order
        console().print(baselines_note(note))
    for row in rows:
        extrapolation_note(row, Path(row["dataset"]).name)
        extrapolated_nodes(row, Path(row["dataset"]).name)


def compare_command(
    runs: list[Path] = typer.Argument(..., help="Run folders (runs/<name>)."),
    json_out: bool = _TABLE_JSON,
) -> None:
    """Compare training runs: best epoch, min validation loss, Table-2 figure, test error."""
    from mpnode_cli.report.tables import compare_table
    from mpnode_cli.training.run import read_summary

    try:
        summaries = [read_summary(run) for run in runs]
    except ValueError as exc:
        fail(error_message(exc))
    if json_out:
        typer.echo(json.dumps(summaries, indent=2))
        return
    console().print(compare_table(summaries))


def extrapolated_nodes(row: dict[str, Any], name: str | None = None) -> None:
    """Print on stderr the nodes of a result (evaluate, zeroshot, simulate) outside the
    training range, if any: a count and the worst few
    (`mpnode_cli.training.extrapolation.node_lines`); `name` (the target's) leads the
    count where several targets are reported."""
    from mpnode_cli.training.extrapolation import node_lines

    lines = node_lines(row.get("extrapolation"))
    if lines and name:
        lines[0] = f"{name}: {lines[0]}"
    for line in lines:
        typer.echo(line, err=True)


def _load_checkpoint(path: Path, member: int | None = None):
    """The checkpoint at `path` (`member`: that member of an ensemble's, alone)."""
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.checkpoint_members import member_checkpoint

    try:
        ckpt = load_checkpoint(path)
        return ckpt if member is None else member_checkpoint(ckpt, member)
    except (FileNotFoundError, ValueError) as exc:
        fail(error_message(exc))


def _member(member: int | None) -> dict[str, int]:
    """`--json`'s `member` key: there only with `--member`."""
    return {} if member is None else {"member": member}


def _named(checkpoint: Path, member: int | None) -> str:
    """A checkpoint as a table's title names it."""
    return str(checkpoint) if member is None else f"{checkpoint} (member {member})"


def _check_batch_size(batch_size: int) -> None:
    if batch_size < 1:
        fail(f"--batch-size must be at least 1, got {batch_size}")


def _evaluate(ckpt, dataset: Path, split: str, verb: str, batch_size: int, device: str,
              plot_dir: Path | None, allow_other_system: bool = False,
              save_predictions: Path | None = None, force: bool = False,
              quiet: bool = False, by_degree: bool = False) -> dict[str, Any]:
    """`evaluate_checkpoint` of one dataset behind a progress bar, its errors as the
    user's one line and exit code."""
    from mpnode_cli.cli.common import task_bar
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.devices import torch_device
    from mpnode_cli.training.checkpoint_report import evaluate_checkpoint
    from mpnode_cli.training.predict import PredictionFailed

    try:
        torch_device(device)
        data = TrajectoryData.load(dataset)
        with task_bar(f"{verb} {dataset.name}", quiet=quiet) as (_, progress):
            return evaluate_checkpoint(ckpt, data, split=split, verb=verb,
                                       batch_size=batch_size, device=device,
                                       plot_dir=plot_dir, allow_other_system=allow_other_system,
                                       save_predictions=save_predictions, overwrite=force,
                                       by_degree=by_degree, progress=progress)
    except (FileNotFoundError, FileExistsError, ValueError) as exc:
        fail(error_message(exc))
    except PredictionFailed as exc:
        fail(str(exc), code=1)
    except OSError as exc:  # a plot that could not be written after all
        fail(f"cannot write {exc.filename or 'a plot'}: {exc.strerror or exc}")
    except KeyboardInterrupt as exc:  # Ctrl-C, or a signal held while predictions were written
        from mpnode_cli.signals import exit_code

        typer.echo("Interrupted", err=True)
        raise typer.Exit(code=exit_code(exc)) from None


def _degree_caption(row: dict[str, Any]) -> str:
    """What `evaluate --by-degree`'s table is of: units, and the in-degrees of training."""
    trained = (row.get("extrapolation") or {}).get("train_in_degree")
    span = f"; in-degree {trained[0]}–{trained[1]} in training" if trained else ""
    return (f"MSE in physical units beside the naive predictors', skill = MSE / time-mean "
            f"MSE, outside: share of node-trajectories leaving the training states{span}")


def _default_plot_dir(checkpoint: Path) -> Path:
    """`runs/<name>/plots` for `runs/<name>/checkpoints/x.pt`, else beside the checkpoint."""
    parent = checkpoint.resolve().parent
    return (parent.parent if parent.name == "checkpoints" else parent) / "plots"
