"""`mpnode import --states S --adjacency A | --edge-list E --dt DT`: your arrays as a dataset.

The command parses, builds an `ImportConfig` and calls
`mpnode_cli.data.importers.import_arrays`; every input that cannot be used is one line and
exit 2, before anything is written. Ctrl-C and SIGTERM leave no file (130 / 143).
"""

from __future__ import annotations

from pathlib import Path

import typer

from mpnode_cli.cli.common import console, output_parser, warn
from mpnode_cli.terminal import suggested


def import_command(
    states: Path = typer.Option(
        ..., help="Trajectories [K, T, N, D]: .npy, .npz (array 'states', optional 'time') "
        "or a long CSV with columns trajectory, time, node and one per state.",
        show_default=False),
    adjacency: Path | None = typer.Option(
        None, help="Graph(s) as .npy: [N, N] for all trajectories or [K, N, N] one each; "
        "A[i, j] = 1 iff node j sends to node i."),
    edge_list: Path | None = typer.Option(
        None, help="Graph as a text file of 'i j' lines (optional weight column, 0 or 1), "
        "undirected unless --directed (docs/dataset-format.md)."),
    directed: bool = typer.Option(
        False, "--directed", help="Read the edge list's 'i j' as one edge i → j."),
    dt: float = typer.Option(..., help="Sample spacing.", show_default=False),
    controls: Path | None = typer.Option(
        None, help="Zero-order-hold controls [K, T, N, U] as .npy."),
    state_names: str | None = typer.Option(
        None, help="Comma-separated names of the D states (default: the CSV's columns, "
        "else x0, x1, ...)."),
    control_names: str | None = typer.Option(
        None, help="Comma-separated names of the U controls (default u0, u1, ...)."),
    periodic: list[str] | None = typer.Option(
        None, "--periodic", help="A state that is an angle (mod 2π), by name; repeat for "
        "more. Recorded as the dataset's periodic_states (docs/dataset-format.md).",
        show_default=False),
    split: str | None = typer.Option(
        None, help="Train,validation,test fractions (default 0.7,0.15,0.15)."),
    seed: int | None = typer.Option(None, help="Seed of the split (default 0)."),
    dtype: str | None = typer.Option(None, help="Storage dtype: float32 (default) or float64."),
    out: Path | None = typer.Option(
        None, help="Output file (default datasets/<states>.h5); a path ending in / is "
        "refused: name the file.", parser=output_parser("--out")),
    force: bool = typer.Option(
        False, "--force", help="Overwrite an existing output file (regular files only)."),
    json_out: bool = typer.Option(
        False, "--json", help="Print the summary as one JSON object on stdout."),
) -> None:
    """Turn your own trajectories and graph into an mpnode dataset (system "custom")."""
    options = dict(locals())  # the parameters, before any other local name
    import json

    from mpnode_cli.cli.common import config_from, split_by_name, with_bar
    from mpnode_cli.config import ImportConfig
    from mpnode_cli.data.importers import import_arrays
    from mpnode_cli.data.splits import split_warning

    config = config_from(ImportConfig, options)
    summary = with_bar(f"importing {states.name}",
                       lambda progress: import_arrays(config, overwrite=force, progress=progress),
                       quiet=json_out, stopped="nothing written")
    empty = split_warning(summary.split_counts, config.split)
    if empty:
        warn(empty)
    if json_out:
        typer.echo(json.dumps({
            "path": str(summary.path), "trajectories": summary.trajectories,
            "split": split_by_name(summary.split_counts), "samples": summary.samples,
            "num_nodes": summary.nodes, "node_dim": summary.node_dim,
            "control_dim": summary.control_dim, "graphs": summary.graphs,
            "fingerprint": summary.fingerprint}))
        return
    train, val, test = summary.split_counts
    console().print(
        f"wrote {summary.path}: {summary.trajectories} trajectories ({train} train / {val} "
        f"val / {test} test) × {summary.samples} samples × {summary.nodes} nodes × "
        f"{summary.node_dim} states"
        + (f", {summary.control_dim} controls" if summary.control_dim else "")
        + f", {summary.graphs} graph{'s' * (summary.graphs > 1)}", highlight=False)
    console().print(f"fingerprint {summary.fingerprint}; check it with: "
                    f"{suggested('check', Path(summary.path))}", highlight=False, markup=False)
