"""`mpnode simulate CKPT --x0 X0.npy --adjacency A.npy | --edge-list E --t-end T --dt DT`:
a trained node model on graphs nobody has data for.

The command parses, builds a `SimulateConfig` and calls
`mpnode_cli.training.predict.simulate`, which writes the predictions as an
`mpnode-dataset` file (docs/dataset-format.md, "Predictions"). Before a big rollout it
prints the size and memory it will take and asks to go on, as `generate` does (`--yes`
answers for a script). Exit 2 for anything the user can fix, 1 when rollouts did not
finish, 130 / 143 for Ctrl-C / SIGTERM (nothing written).
"""

from __future__ import annotations

from pathlib import Path

import typer

from mpnode_cli.cli.common import (
    MEMBER,
    THREADS,
    confirm_size,
    console,
    error_message,
    extrapolation_note,
    fail,
    output_parser,
)


def simulate_command(
    checkpoint: Path = typer.Argument(
        ..., help="A checkpoint (.pt), or a run folder (its best.pt)."),
    x0: Path = typer.Option(
        ..., "--x0", help="Initial states [K, N, D] (or [N, D]) in physical units, .npy.",
        show_default=False),
    adjacency: Path | None = typer.Option(
        None, help="Graph(s) as .npy: [N, N] for all or [K, N, N] one per trajectory."),
    edge_list: Path | None = typer.Option(
        None, help="Graph as a text file of 'i j' lines, undirected unless --directed."),
    directed: bool = typer.Option(
        False, "--directed", help="Read the edge list's 'i j' as one edge i → j."),
    t_end: float = typer.Option(..., help="Last sample time (samples 0, dt, ..).",
                                show_default=False),
    dt: float = typer.Option(..., help="Sample spacing.", show_default=False),
    controls: Path | None = typer.Option(
        None, help="Controls [K, T, N, U] in physical units (zero-order hold), .npy."),
    out: Path | None = typer.Option(
        None, help="Output file (default predictions/<x0 file name>.h5); a path ending in / "
        "is refused: name the file.", parser=output_parser("--out")),
    force: bool = typer.Option(
        False, "--force", help="Overwrite an existing output file (regular files only)."),
    batch_size: int | None = typer.Option(None, help="Trajectories per rollout (128)."),
    device: str | None = typer.Option(None, help="cpu (default) or cuda."),
    dtype: str | None = typer.Option(None, help="Storage dtype: float32 (default) or float64."),
    yes: bool = typer.Option(
        False, "--yes", "-y", help="Go ahead with a big job without asking."),
    json_out: bool = typer.Option(
        False, "--json", help="Print the summary as one JSON object on stdout."),
    member: int | None = MEMBER,
    threads: str | None = THREADS,
) -> None:
    """Roll a trained model out from your initial states on your graph (no data needed)."""
    options = dict(locals())  # the parameters, before any other local name
    import json
    from dataclasses import asdict

    from mpnode_cli.cli.common import config_from, with_bar
    from mpnode_cli.cli.evaluate import extrapolated_nodes
    from mpnode_cli.config import SimulateConfig
    from mpnode_cli.devices import torch_device
    from mpnode_cli.training.predict import PredictionFailed, simulate

    config = config_from(SimulateConfig, options)
    try:
        torch_device(config.device)
    except ValueError as exc:
        fail(error_message(exc))
    summary = with_bar(f"simulating {x0.name}",
                       lambda progress: simulate(
                           config, overwrite=force, progress=progress,
                           confirm=lambda size, job: confirm_size(size, job, yes)),
                       quiet=json_out, stopped="nothing written", failures=(PredictionFailed,))
    record = asdict(summary)
    if record["members"] is None:  # a single model's summary, as before ensembles
        del record["members"]
    if json_out:
        typer.echo(json.dumps({**record, "path": str(summary.path)}))
        return
    console().print(
        f"wrote {summary.path}: {summary.trajectories} predicted trajectories × "
        f"{summary.samples} samples × {summary.nodes} nodes on {summary.graphs} "
        f"graph{'s' * (summary.graphs > 1)} ({summary.seconds:.2f} s, "
        f"{summary.n_f_evals:,} RHS evaluations)", highlight=False)
    if summary.members:
        console().print(f"the states are the mean of the ensemble's {summary.members} "
                        "members; their std is hidden/ensemble_std", highlight=False)
    extrapolation_note(record)
    extrapolated_nodes(record)
