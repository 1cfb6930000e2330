"""`mpnode check FILE`: validate a dataset or a checkpoint completely.

Exit 0 with a short summary when the file is valid, 2 with one line per problem when it is
not. `--json` prints the report as one JSON object on stdout instead (either way).

`mpnode check CKPT --member K --out FILE` also writes member K of a valid ensemble
checkpoint (`train --seeds S`) as a checkpoint of one model
(`mpnode_cli.training.checkpoint_members.export_member`), which every verb takes as it takes
`--member K` with the ensemble.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

from mpnode_cli.cli.common import console, error_message, fail, output_parser

_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_ZIP_SIGNATURE = b"PK\x03\x04"
# Names a dataset goes by: such a file that is not HDF5 is named so, not tried as a checkpoint.
_HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf")


def check_command(
    path: Path = typer.Argument(
        ..., metavar="FILE", help="A dataset (.h5), a checkpoint (.pt) or a run folder."),
    json_out: bool = typer.Option(False, "--json", help="Print the report as JSON."),
    deep: bool = typer.Option(
        False, "--deep", help="A dataset: read every byte, verifying its checksums (memory "
        "stays bounded; the time is a read of the whole file)."),
    member: int | None = typer.Option(
        None, "--member", metavar="K", show_default=False,
        help="With --out: write member K of an ensemble checkpoint as a checkpoint of its "
        "own."),
    out: Path | None = typer.Option(
        None, "--out", metavar="FILE", show_default=False,
        help="Where --member's checkpoint goes (.pt; a path ending in / is refused).",
        parser=output_parser("--out")),
    force: bool = typer.Option(False, "--force", help="Overwrite an existing --out file."),
) -> None:
    """Check a dataset or checkpoint: shapes, indices, attributes, finite values, format."""
    if (member is None) != (out is None):
        fail("--member and --out go together: mpnode check CKPT --member K --out FILE "
             "writes member K of an ensemble as a checkpoint of its own")
    report = _check(path, deep)
    exported = _export(report, member, out, force) if report.ok and out is not None else None
    if json_out:
        typer.echo(json.dumps(report.to_dict() | ({"exported": exported} if exported else {}),
                              default=str))
    elif report.ok:
        console().print(f"{report.path}: valid {report.kind}")
        for key, value in report.summary.items():
            console().print(f"  {key}: {_shown(value)}", highlight=False)
        if exported:
            console().print(f"wrote {exported['path']}: member {member} (seed "
                            f"{exported['seed']}) as a checkpoint of one model",
                            highlight=False)
    else:
        for problem in report.problems:  # the file named once
            named = problem.startswith(str(report.path))
            typer.echo(f"Error: {'' if named else f'{report.path}: '}{problem}", err=True)
    if not report.ok:
        raise typer.Exit(code=2)


def _export(report, member: int, out: Path, force: bool) -> dict:
    """Write member `member` of the checked checkpoint to `out`: what `--json` adds as
    `exported` (path, member, seed); a refusal is one line and exit 2."""
    from mpnode_cli.training.checkpoint_members import export_member

    if report.kind != "checkpoint":
        fail(f"--member: {report.path} is a {report.kind}, not an ensemble checkpoint")
    if out.suffix.lower() in _HDF5_SUFFIXES:  # every reader would take it for a dataset
        fail(f"--out {out}: a checkpoint is a .pt file, and {out.suffix} names a dataset")
    try:
        ckpt = export_member(report.path, member, out, overwrite=force)
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        fail(error_message(exc))
    return {"path": str(out), "member": member, "seed": ckpt.train_config.get("seed")}


def _check(path: Path, deep: bool = False):
    from mpnode_cli.data.validate import Report, check_dataset
    from mpnode_cli.paths import begins

    if not path.exists():
        return Report(path, "file", [f"no such file or folder: {path}"])
    if path.is_file() and path.stat().st_size == 0:
        return Report(path, "file", [f"{path} is an empty file (0 bytes): neither a dataset "
                                     "nor a checkpoint"])
    if path.is_file() and begins(path, _HDF5_SIGNATURE):
        return check_dataset(path, deep=deep)
    if (path.is_file() and path.suffix.lower() in _HDF5_SUFFIXES
            and not begins(path, _ZIP_SIGNATURE)):
        import h5py  # an HDF5 file may start after a user block: h5py looks further

        if h5py.is_hdf5(path):
            return check_dataset(path, deep=deep)
        return Report(path, "file", [f"{path} is not an HDF5 file (it lacks HDF5's "
                                     "signature), so not an mpnode dataset"])
    from mpnode_cli.training.checkpoint_check import check_checkpoint

    return check_checkpoint(path)


def _shown(value) -> str:
    if isinstance(value, dict):
        return ", ".join(f"{k} {_shown(v)}" for k, v in value.items() if v is not None)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)
