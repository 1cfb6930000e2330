"""`mpnode simulate`: a checkpoint's model rolled out from a user's initial states on a
user's graph, the predictions written as an `mpnode-dataset` file (`simulate`).

The rollouts and the file are `mpnode_cli.training.predict`'s (`roll_out`,
`write_predictions`); beside them the file holds the per-node flags of the predicted
states and in-degrees outside the checkpoint's training range
(`mpnode_cli.training.extrapolation`). No ground truth is needed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.hdf5 import BLOCK_VALUES
from mpnode_cli.data.size import SizeEstimate, check_job, simulate_estimate
from mpnode_cli.file_records import file_sha256
from mpnode_cli.memory import naming_memory
from mpnode_cli.progress import Progress
from mpnode_cli.report.members import shown
from mpnode_cli.training.predict import check_finished, roll_out, rollout_solver, write_predictions


@dataclass(frozen=True)
class SimulateSummary:
    """What `simulate` wrote.

    Attributes:
        path: the prediction file. trajectories, samples, nodes: K, T, N.
        graphs: distinct graphs. n_f_evals: vector-field evaluations, summed over
            trajectories. seconds: wall time of the rollouts.
        extrapolation: the graphs and the predicted states against the checkpoint's
            training range, as a whole and node by node
            (`mpnode_cli.training.extrapolation.Extrapolation.to_dict`), or None for a
            checkpoint without one.
        members: S of an ensemble whose mean was written (with `hidden/ensemble_std`);
            None for one model (a single model's checkpoint, or `member`).
    """

    path: Path
    trajectories: int
    samples: int
    nodes: int
    graphs: int
    n_f_evals: int
    seconds: float
    extrapolation: dict[str, Any] | None = None
    members: int | None = None


def simulate(config, *, overwrite: bool = False,
             confirm: Callable[[SizeEstimate, str], None] | None = None,
             progress: Progress | None = None) -> SimulateSummary:
    """Roll a checkpoint's model out from a user's initial states on a user's graph, and
    write the predictions (`mpnode simulate`). No ground truth is needed.

    Args:
        config: a `mpnode_cli.config.simulate.SimulateConfig`.
        overwrite: replace an existing regular file at the output path.
        confirm: called as `confirm(estimate, "K trajectories × T samples × N nodes")`
            once the inputs are read and before anything is sized by the horizon; it
            raises `ValueError` to stop (the CLI asks about big jobs there).
        progress: called after each batch of rollouts with the trajectories done and K.

    Raises:
        FileNotFoundError, ValueError: a checkpoint, input or output that cannot be used,
            or a job larger than this machine's memory (one line; all checked before any
            rollout; the output is checked and reserved before any rollout, and may be none
            of the inputs, `mpnode_cli.paths.reserve_output`).
        FileExistsError: the output exists and `overwrite` is False.
        PredictionFailed: rollouts that did not finish (nothing written).
        KeyboardInterrupt: SIGINT or SIGTERM (nothing written).
    """
    from mpnode_cli.paths import reserve_output
    from mpnode_cli.training.checkpoint import resolve_path

    out = simulate_output(config)
    try:
        checkpoint = resolve_path(config.checkpoint)  # a run folder's best.pt
    except FileNotFoundError:  # load_checkpoint says so, once the output is checked
        checkpoint = config.checkpoint
    inputs = (checkpoint, config.x0, config.adjacency, config.edge_list, config.controls)
    with reserve_output(out, overwrite=overwrite, inputs=inputs):
        return _simulate(config, out, confirm, progress)


def _simulate(config, out: Path, confirm, progress: Progress | None) -> SimulateSummary:
    """`simulate` once its output is reserved: load, roll out, write."""
    import time as clock

    from mpnode_cli.data.user_inputs import load_controls, load_graph, load_initial_states
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.checkpoint_members import member_checkpoint
    from mpnode_cli.training.extrapolation import extrapolation

    ckpt = load_checkpoint(config.checkpoint)
    if config.member is not None:
        ckpt = member_checkpoint(ckpt, config.member)
    x0 = load_initial_states(config.x0)
    k, n, _ = x0.shape
    graphs, graph_index = load_graph(config.adjacency, config.edge_list, k, n,
                                     directed=config.directed)
    size = simulate_estimate(ckpt, k, config.num_steps + 1, n, config.dtype,
                             batch_size=config.batch_size, solver=rollout_solver(ckpt),
                             dt=config.dt)
    check_job(size, "this simulation", "lower --t-end or the number of initial states, "
              "or raise --dt", solver=rollout_solver(ckpt))
    if confirm is not None:
        confirm(size, f"{k} trajectories × {config.num_steps + 1} samples × {n} nodes")
    ts = np.arange(config.num_steps + 1) * config.dt  # [T]
    controls = None
    if config.controls is not None:
        controls = load_controls(config.controls, (k, len(ts), n))
    start = clock.perf_counter()
    with naming_memory(f"rolling out {k} trajectories in batches of {config.batch_size}",
                       size.memory_bytes, "lower --batch-size, --t-end or the number of "
                       "initial states"):
        pred = roll_out(ckpt, x0, ts, graphs, graph_index, controls,
                        batch_size=config.batch_size, device=config.device, progress=progress)
    seconds = clock.perf_counter() - start
    check_finished(pred)
    beyond = extrapolation(ckpt, graphs, graph_index, _in_blocks(pred.states), predicted=True)
    sources = {name: {"path": str(Path(path).resolve()), "sha256": file_sha256(path)}
               for name in ("x0", "adjacency", "edge_list", "controls")
               if (path := getattr(config, name)) is not None}
    resolved = config.model_copy(update={"out": out}).model_dump(mode="json")
    write_predictions(out, ckpt, pred, time=ts, graphs=graphs, graph_index=graph_index,
                      controls=controls, config={"verb": "simulate", **resolved,
                                                 "topology": _topology(config)},
                      source=sources, dtype=config.dtype,
                      overwrite=True,  # over the reservation `simulate` made
                      node_flags=None if beyond is None else beyond.nodes.flags)
    return SimulateSummary(path=out, trajectories=k, samples=len(ts), nodes=n,
                           graphs=len(graphs), n_f_evals=int(pred.n_f_evals.sum()),
                           seconds=seconds,
                           extrapolation=None if beyond is None else beyond.to_dict(),
                           members=shown(ckpt.members, ckpt.members))


def simulate_output(config) -> Path:
    """`config.out`, or `predictions/<x0 file stem>.h5`."""
    return Path(config.out) if config.out is not None else Path(
        "predictions", f"{Path(config.x0).stem}.h5")


def _topology(config) -> str:
    return "edgelist" if config.edge_list is not None else "adjacency"


def _in_blocks(states: np.ndarray):
    """`[K, T, N, D]` predictions as tensors of a few trajectories each (views, no copy),
    for `mpnode_cli.training.extrapolation.extrapolation`."""
    rows = max(1, BLOCK_VALUES // max(int(np.prod(states.shape[1:])), 1))
    return (torch.from_numpy(states[start:start + rows])
            for start in range(0, len(states), rows))
