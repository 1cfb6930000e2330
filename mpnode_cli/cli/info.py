"""`mpnode info FILE`: a dataset's summary, read from its header without loading states."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer


def info_command(
    path: Path = typer.Argument(..., metavar="FILE", help="An mpnode dataset (.h5)."),
    json_out: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
) -> None:
    """Print a dataset's summary (after checking the file, as `mpnode check` does)."""
    import json

    from rich.console import Console
    from rich.table import Table

    from mpnode_cli.data.hdf5 import DatasetFormatError, read_header
    from mpnode_cli.data.validate import require_valid

    try:
        require_valid(path)
        header = read_header(path)
    except (FileNotFoundError, DatasetFormatError) as exc:
        typer.echo(f"Error: {exc}", err=True)
        raise typer.Exit(code=2) from None

    if json_out:
        typer.echo(json.dumps({"path": str(path), **dict(_rows(header))}))
        return
    table = Table(title=str(path), show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    for name, value in _rows(header):
        table.add_row(name, value)
    Console().print(table)


def _rows(header: dict[str, Any]) -> list[tuple[str, str]]:
    """(label, text) rows of the summary table."""
    import numpy as np

    from mpnode_cli.config import generate_solver, stored_solver

    attrs, shapes, config = header["attrs"], header["shapes"], header["attrs"]["config"]
    (k, t, n, d), states_dtype = shapes["states"]
    adjacency = header["adjacency"]  # [G, N, N]
    train, val, test = np.bincount(header["split"], minlength=3)[:3]
    directed = not all(np.array_equal(a, a.T) for a in adjacency)
    # An undirected edge is two messages (i → j and j → i); a directed one is one.
    edges = adjacency.reshape(len(adjacency), -1).sum(axis=1) / (1 if directed else 2)
    failed = int(np.count_nonzero(header["solver_status"]))
    scalars = ", ".join(f"{key}={value:g}" for key, value in header["scalar_params"].items())
    solver = stored_solver(config, generate_solver)
    steps = (f"fixed dt {solver.fixed_dt:g}" if solver.fixed_dt is not None
             else f"rtol {solver.rtol:g}, atol {solver.atol:g}")
    per_graph = ", ".join(
        f"{name.removeprefix('params/')} {list(shape)}"
        for name, (shape, _) in shapes.items()
        if name.startswith("params/")
    )
    rows = [
        ("format", f"{attrs['format']} v{attrs['format_version']}"),
        ("system", attrs["system"]),
        ("nodes × state", f"{n} × {d} ({', '.join(attrs['state_names'])})"),
        ("controls", ", ".join(attrs["control_names"]) or "none"),
        ("trajectories", f"{k} ({train} train / {val} val / {test} test)"),
        ("samples", f"{t} (dt {attrs['dt']:g}, t_end {attrs['dt'] * (t - 1):g})"),
        (
            "graphs",
            f"{len(adjacency)} × {config.get('topology', '?')}, {edges.mean():g} "
            f"{'directed' if directed else 'undirected'} edges on average",
        ),
        ("parameters", scalars or "none"),
        ("per-graph parameters", per_graph or "none"),
        ("states dtype", states_dtype),
        ("seeds", f"trajectories {_known(attrs['seed'])}, "
                  f"graphs {_known(config.get('graph_seed'))}"),
        (
            "solver",
            f"{solver.method}, {steps}, {failed} unfinished in the file",
        ),
    ]
    if "n_rejected" in attrs:
        rows.append(
            ("redrawn", f"{attrs.get('n_failed', 0)} failed, {attrs['n_rejected']} rejected")
        )
    hidden = [name.removeprefix("hidden/") for name in shapes if name.startswith("hidden/")]
    if hidden:
        rows.append(("hidden states", ", ".join(hidden)))
    version = attrs["mpnode_version"]
    writer = f"mpnode {version}" if version else "?"
    rows.append(("written", f"{_known(attrs['created_utc'])} by {writer}"))
    return rows


def _known(value: Any) -> str:
    return "?" if value is None else str(value)
