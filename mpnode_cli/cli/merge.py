"""`mpnode merge SHARDS... -o OUT`: join the shards of `mpnode generate --shard i/n`.

The command only parses and reports; `mpnode_cli.data.shards.merge_shards` checks that the
files are every shard of one dataset and writes the merged file atomically. Exit codes: 2
for files that do not belong together or an unusable output path, 130 for Ctrl-C and 143
for SIGTERM (either leaves nothing at the output path). h5py is imported inside the
function.
"""

from __future__ import annotations

from pathlib import Path

import typer

from mpnode_cli.cli.common import FORCE, JSON_OUT, console, output_parser


def merge_command(
    shards: list[Path] = typer.Argument(
        ..., metavar="SHARDS...", show_default=False,
        help="Every shard file of one dataset (the *.shard-000i-of-000n.h5 that mpnode "
        "generate --shard writes), in any order."),
    out: Path = typer.Option(
        ..., "--out", "-o", show_default=False,
        help="The merged dataset file: the file generate without --shard would write (a "
        "path ending in / is refused: name the file).", parser=output_parser("--out")),
    virtual: bool = typer.Option(
        False, "--virtual",
        help="Write an HDF5 virtual dataset that reads the trajectories from the shards "
        "instead of copying them (fast, no second copy on disk). The shards must then stay "
        "where they are: the file finds them by their paths relative to its own folder."),
    force: bool = FORCE,
    json_out: bool = JSON_OUT,
) -> None:
    """Merge the shards of one dataset into one dataset file."""
    import json

    from mpnode_cli.cli.common import with_bar
    from mpnode_cli.data.shards import merge_shards
    from mpnode_cli.memory import format_bytes

    summary = with_bar(f"merging {len(shards)} shards",
                       lambda progress: merge_shards(shards, out, overwrite=force,
                                                     virtual=virtual, progress=progress),
                       quiet=json_out, stopped=f"nothing written to {out}")
    if json_out:
        typer.echo(json.dumps({"path": str(summary.path), "shards": summary.shards,
                               "trajectories": summary.trajectories,
                               "virtual": summary.virtual, "redrawn": summary.redrawn,
                               "bytes": summary.bytes}))
        return
    how = "mapped (virtual; keep the shards in place)" if summary.virtual else "copied"
    console().print(f"wrote {summary.path}: {summary.trajectories} trajectories from "
                    f"{summary.shards} shards, {format_bytes(summary.bytes)} {how}",
                    highlight=False)
    if summary.redrawn:
        console().print(
            f"note: the shards redrew {summary.redrawn} trajectories from their own "
            "generators, so those differ from a single-file generate of this config",
            highlight=False)
