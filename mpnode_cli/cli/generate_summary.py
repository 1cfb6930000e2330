"""What `mpnode generate` prints when the dataset is written: a table of what it holds and
what it cost (`print_summary`), or the same as one JSON line (`print_json`, `--json`).
"""

from __future__ import annotations

from typing import Any

import typer

from mpnode_cli.cli.common import console, split_by_name
from mpnode_cli.threads import applied_threads


def print_json(config: Any, summary: Any) -> None:
    import json

    typer.echo(json.dumps({
        "path": str(summary.path), "system": config.system, "num_nodes": config.nodes,
        "topology": config.topology, "graphs": config.graphs,
        "trajectories": summary.trajectories, "split": split_by_name(summary.split_counts),
        "samples": config.num_steps + 1, "dt": config.dt, "t_end": config.t_end,
        "failed": summary.failed, "rejected": summary.rejected,
        "n_f_evals": summary.n_f_evals, "seconds": summary.seconds,
        "solve_seconds": summary.solve_seconds,
        "shard": None if config.shard is None else list(config.shard),
    }))


def print_summary(config: Any, summary: Any) -> None:
    from mpnode_cli.report.tables import titled

    train, val, test = summary.split_counts
    table = titled(f"wrote {summary.path}", show_header=False)
    table.add_column(style="bold")
    table.add_column(justify="right")
    rows = [
        ("system", f"{config.system} on {config.graphs} × {config.topology}"),
        ("nodes", str(config.nodes)),
        ("trajectories", f"{summary.trajectories} ({train} train / {val} val / {test} test)"),
        ("samples", f"{config.num_steps + 1} (dt {config.dt:g}, t_end {config.t_end:g})"),
        ("failed / rejected", f"{summary.failed} / {summary.rejected} (redrawn)"),
        ("RHS evaluations", f"{summary.n_f_evals:,}"),
        ("seconds", f"{summary.seconds:.2f} ({summary.solve_seconds:.2f} solving)"),
    ]
    if config.shard is not None:
        from mpnode_cli.data.generate import trajectory_range

        (index, count), (start, stop) = config.shard, trajectory_range(config)
        rows.insert(3, ("shard", f"{index} of {count}: trajectories {start}–{stop - 1} of "
                                 f"{config.trajectories}"))
    for row in rows:
        table.add_row(*row)
    console().print(table)
    if threads := applied_threads():
        typer.echo(f"threads: {threads.describe()}")
