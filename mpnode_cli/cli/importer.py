"""`mpnode import --states S --adjacency A | --edge-list E --dt DT`: your arrays as a dataset.

The command parses, builds an `ImportConfig` and calls
`mpnode_cli.data.importers.import_arrays`; every input that cannot be used is one line and
exit 2, before anything is written. Ctrl-C and SIGTERM leave no file (130 / 143).
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import typer

from mpnode_cli.cli.common import FORCE, JSON_OUT, console, output_parser, warn
from mpnode_cli.cli.options import field_default, field_parameter, with_options
from mpnode_cli.config.importer import ImportConfig
from mpnode_cli.terminal import suggested

DATA, WRITTEN = "Your data", "The dataset written"
_PANELS = {
    DATA: ("states", "adjacency", "edge_list", "directed", "dt", "controls", "state_names",
           "control_names", "periodic"),
    WRITTEN: ("split", "seed", "dtype", "out", "force", "json_out"),
}


def import_command(
    periodic: list[str] | None = typer.Option(
        None, "--periodic", metavar="NAME", show_default=False,
        help=ImportConfig.model_fields["periodic"].description),
    force: bool = FORCE,
    json_out: bool = JSON_OUT,
    **options: Any,
) -> None:
    """Turn your own trajectories and graph into an mpnode dataset (system "custom")."""
    import json

    from mpnode_cli.cli.common import config_from, split_by_name, with_bar
    from mpnode_cli.data.importers import import_arrays
    from mpnode_cli.data.splits import split_warning

    config = config_from(ImportConfig, {**options, "periodic": periodic})
    summary = with_bar(f"importing {config.states.name}",
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


def _field(name: str, panel: str) -> inspect.Parameter:
    """The option of `ImportConfig`'s field `name` (names and fractions as the command
    line writes them, comma-separated)."""
    return field_parameter(
        ImportConfig, name, panel, default=field_default(ImportConfig, name),
        value_type=str if name in ("split", "state_names", "control_names") else None,
        parser=output_parser("--out") if name == "out" else None)


import_command = with_options(import_command, _PANELS, _field)
