"""`mpnode check FILE`: validate a dataset or a checkpoint completely.

Exit 0 with a short summary when the file is valid, 2 with one line per problem when it is
not. `--json` prints the report as one JSON object on stdout instead (either way).
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from mpnode_cli.cli.common import console

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"


def check_command(
    path: Path = typer.Argument(
        ..., metavar="FILE", help="A dataset (.h5), a checkpoint (.pt) or a run folder."),
    json_out: bool = typer.Option(False, "--json", help="Print the report as JSON."),
) -> None:
    """Check a dataset or checkpoint: shapes, indices, attributes, finite values, format."""
    report = _check(path)
    if json_out:
        typer.echo(json.dumps(report.to_dict(), default=str))
    elif report.ok:
        console().print(f"{report.path}: valid {report.kind}")
        for key, value in report.summary.items():
            console().print(f"  {key}: {_shown(value)}", highlight=False)
    else:
        for problem in report.problems:
            typer.echo(f"Error: {report.path}: {problem}", err=True)
    if not report.ok:
        raise typer.Exit(code=2)


def _check(path: Path):
    from mpnode_cli.data.validate import Report, check_dataset

    if not path.exists():
        return Report(path, "file", [f"no such file or folder: {path}"])
    if path.is_file() and _is_hdf5(path):
        return check_dataset(path)
    from mpnode_cli.training.validate import check_checkpoint

    return check_checkpoint(path)


def _is_hdf5(path: Path) -> bool:
    """HDF5's signature at the file's start (where mpnode and h5py put it)."""
    try:
        with open(path, "rb") as f:
            return f.read(len(_HDF5_SIGNATURE)) == _HDF5_SIGNATURE
    except OSError:
        return False


def _shown(value) -> str:
    if isinstance(value, dict):
        return ", ".join(f"{k} {_shown(v)}" for k, v in value.items() if v is not None)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)
