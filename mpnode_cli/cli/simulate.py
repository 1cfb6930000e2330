"""`mpnode simulate CKPT --x0 X0.npy --adjacency A.npy | --edge-list E --t-end T --dt DT`:
a trained node model on graphs nobody has data for.

The command parses, builds a `SimulateConfig` and calls
`mpnode_cli.training.simulate.simulate`, which writes the predictions as an
`mpnode-dataset` file (docs/dataset-format.md, "Predictions"). Before a big rollout it
prints the size and memory it will take and asks to go on, as `generate` does (`--yes`
answers for a script). Exit 2 for anything the user can fix, 1 when rollouts did not
finish, 130 / 143 for Ctrl-C / SIGTERM (nothing written).
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any

import typer

from mpnode_cli.cli.common import (
    FORCE,
    JSON_OUT,
    MEMBER,
    THREADS,
    YES,
    confirm_size,
    console,
    error_message,
    extrapolation_note,
    fail,
    output_parser,
)
from mpnode_cli.cli.options import field_default, field_parameter, with_options
from mpnode_cli.config.simulate import SimulateConfig

INPUTS, ROLLOUT = "Model, initial states and graph", "Rollout and output"
_PANELS = {
    INPUTS: ("x0", "adjacency", "edge_list", "directed", "controls", "member"),
    ROLLOUT: ("t_end", "dt", "batch_size", "device", "dtype", "out", "force", "yes",
              "json_out", "threads"),
}


def simulate_command(
    checkpoint: Path = typer.Argument(
        ..., help=SimulateConfig.model_fields["checkpoint"].description),
    force: bool = FORCE,
    yes: bool = YES,
    json_out: bool = JSON_OUT,
    member: int | None = MEMBER,
    threads: str | None = THREADS,
    **options: Any,
) -> None:
    """Roll a trained model out from your initial states on your graph (no data needed)."""
    import json
    from dataclasses import asdict

    from mpnode_cli.cli.common import config_from, with_bar
    from mpnode_cli.cli.evaluate import extrapolated_nodes
    from mpnode_cli.devices import torch_device
    from mpnode_cli.training.predict import PredictionFailed
    from mpnode_cli.training.simulate import simulate

    config = config_from(SimulateConfig, {**options, "checkpoint": checkpoint,
                                           "member": member})
    try:
        torch_device(config.device)
    except ValueError as exc:
        fail(error_message(exc))
    summary = with_bar(f"simulating {config.x0.name}",
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


def _field(name: str, panel: str) -> inspect.Parameter:
    """The option of `SimulateConfig`'s field `name`."""
    return field_parameter(
        SimulateConfig, name, panel, default=field_default(SimulateConfig, name),
        parser=output_parser("--out") if name == "out" else None)


simulate_command = with_options(simulate_command, _PANELS, _field)
