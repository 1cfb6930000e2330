"""A trained model's predictions as an `mpnode-dataset` file: what `mpnode simulate`
(`mpnode_cli.training.simulate`) and `mpnode evaluate --save-predictions` write.

`roll_out` predicts trajectories from initial states in physical units, on any graphs, with
the checkpoint's normalization and solver, in batches. `write_predictions` stores them in
the dataset format (docs/dataset-format.md), so that `info`, `check`, `evaluate --plot` and
any h5py reader take them as they take data:

- `states` are the predictions in physical units (not ground truth);
- `hidden/messages [K, T, N, M]` the model's message states (MP-NODE; in the model's own,
  normalized units; an ensemble's: its first member's);
- an ensemble checkpoint's (`mpnode train --seeds S`): `states` are its members' mean, and
  `hidden/ensemble_std [K, T, N, D]` their standard deviation (population, over the S
  members) in physical units;
- `solver/status` and `solver/n_f_evals` the rollouts' (RHS evaluations: the maximum
  within each trajectory's batch);
- `extrapolation [K, N]` (simulate, for a checkpoint that records its training range):
  uint8 per-node flags, bit 0 (`STATE_OUTSIDE`) a predicted state outside the training
  range at some sample, bit 1 (`IN_DEGREE_OUTSIDE`) an in-degree outside the training
  in-degrees (`mpnode_cli.training.extrapolation_nodes.NodeExtrapolation.flags`);
- `system`, `state_names` and `control_names` are those of the checkpoint's training data,
  so that `evaluate` takes the file without `--allow-other-system`;
- the root attribute `prediction` (JSON) says what made the file: the checkpoint's path and
  sha256, its model, the training data's system and fingerprint, the solver, and what the
  rollouts started from; `config` holds the verb's resolved options.

A rollout that fails (a blown-up solve) has no finite prediction to store, and a dataset
holds only finite values, so failures are refused (`PredictionFailed`) instead of written.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch

from mpnode_cli.config.fields import train_solver
from mpnode_cli.config.upgrade import stored_solver
from mpnode_cli.data.fingerprint import fingerprint
from mpnode_cli.data.hdf5 import Dataset
from mpnode_cli.data.hdf5_write import write_dataset
from mpnode_cli.file_records import file_sha256
from mpnode_cli.graphs.matrices import Graphs
from mpnode_cli.models.base import model_dtype
from mpnode_cli.progress import Progress
from mpnode_cli.report.members import shown
from mpnode_cli.solver.options import SolverOptions

F = TypeVar("F", bound=Callable[..., Any])


class PredictionFailed(RuntimeError):
    """Rollouts the solver could not finish: their predictions are not finite."""


@dataclass(frozen=True)
class Predicted:
    """Predicted trajectories (numpy).

    Attributes:
        states: float64 `[K, T, N, D]` physical units.
        messages: float64 `[K, T, N, M]` message states, or None for a model without them.
        status: int8 `[K]` `mpnode_cli.solver.Status` of each rollout (0: finished).
        n_f_evals: int32 `[K]` vector-field evaluations (the maximum within its batch).
        spread: float64 `[K, T, N, D]` an ensemble's members' std (physical units; `states`
            is then their mean), or None for a single model.
    """

    states: np.ndarray
    messages: np.ndarray | None
    status: np.ndarray
    n_f_evals: np.ndarray
    spread: np.ndarray | None = None


def rollout_solver(ckpt) -> SolverOptions:
    """How a checkpoint's model is integrated outside training: its training solver, not
    compiled (one pass over the data does not pay for compiling the step)."""
    return stored_solver(ckpt.train_config, train_solver).model_copy(update={"compile": False})


def roll_out(ckpt, x0: np.ndarray, ts: np.ndarray, graphs: Graphs, graph_index: np.ndarray,
             controls: np.ndarray | None = None, *, batch_size: int = 128,
             device: str | torch.device = "cpu", progress: Progress | None = None
             ) -> Predicted:
    """Predict trajectories from `x0` with a checkpoint's model (an ensemble's: the
    members' mean, and their spread).

    Args:
        ckpt: a `mpnode_cli.training.checkpoint.Checkpoint`.
        x0: `[K, N, D]` initial states, physical units.
        ts: `[T]` sample times (ts[0] is the time of x0).
        graphs: the graphs; graph_index: `[K]` the graph of each trajectory. A batch's
            graphs go to the model as `[B, N, N]` matrices up to `DENSE_GRAPH_MAX_NODES`
            nodes, as an `EdgeBatch` above.
        controls: `[K, T, N, U]` physical, zero-order hold, or None.
        batch_size: trajectories per rollout.
        device: where the rollouts run.
        progress: called after each batch with the trajectories rolled out and K.

    Raises:
        ValueError: sizes that do not fit the model (one line).
    """
    model, normalizer = ckpt.build_model().to(device), ckpt.build_normalizer()
    dtype, s = model_dtype(model), len(model.members)
    x0 = torch.as_tensor(np.asarray(x0), dtype=torch.float32)
    ts = torch.as_tensor(np.asarray(ts), dtype=torch.float64)
    graph_index = np.asarray(graph_index, dtype=np.int64)
    k, n, d = x0.shape
    u_dim = int(ckpt.model_config.get("control_dim", 0))
    if d != int(ckpt.model_config["node_dim"]):
        raise ValueError(f"the initial states have {d} components per node but the "
                         f"checkpoint's model expects {ckpt.model_config['node_dim']}")
    if u_dim and controls is None:
        raise ValueError(f"the checkpoint's model takes {u_dim} controls per node: give "
                         "--controls [K, T, N, U]")
    if not u_dim and controls is not None:
        raise ValueError("the checkpoint's model takes no controls, yet controls were given")
    if not model.transferable and n != ckpt.dataset.get("num_nodes"):
        raise ValueError(f"model '{ckpt.model_kind}' was trained on "
                         f"{ckpt.dataset.get('num_nodes')} nodes and only runs on graphs of "
                         f"that size, not {n}")
    if model.initial_states > 1:
        raise ValueError(f"model '{ckpt.model_kind}' starts from {model.initial_states} "
                         "states, not one initial state")
    u = None if controls is None else torch.as_tensor(np.asarray(controls), dtype=torch.float32)
    solver = rollout_solver(ckpt)
    states, messages, spreads = [], [], []
    status = np.zeros(k, dtype=np.int8)
    n_f_evals = np.zeros(k, dtype=np.int32)
    model.eval()
    with torch.no_grad():
        for idx in torch.arange(k).split(graphs.rollout_batch(batch_size)):
            x = normalizer.norm_x(x0[idx].to(device)).to(dtype)  # (B, N, D)
            ub = None if u is None else normalizer.norm_u(u[idx].to(device)).to(dtype)
            out = model.rollout(x, ts.to(device), _batch_graph(graphs, graph_index[idx.numpy()],
                                                               device),
                                ub, solver=solver, return_messages=True)
            states.append(normalizer.denorm_x(out.states).double().cpu())  # (B, T, N, D)
            if out.messages is not None:
                messages.append(out.messages.double().cpu())  # (B, T, N, M)
            spreads.append(shown(s, normalizer.denorm_spread(out.spread).double().cpu()))
            status[idx.numpy()] = out.status.cpu().numpy()
            n_f_evals[idx.numpy()] = out.n_f_evals
            if progress is not None:
                progress(int(idx[-1]) + 1, k)
    spread = shown(s, spreads)  # (K, T, N, D) in batches: an ensemble's members' std
    return Predicted(states=torch.cat(states).numpy(),
                     messages=torch.cat(messages).numpy() if messages else None,
                     status=status, n_f_evals=n_f_evals,
                     spread=None if spread is None else torch.cat(spread).numpy())


def _batch_graph(graphs: Graphs, graph_index: np.ndarray, device):
    """A batch's graphs as models take them: float32 `[B, N, N]` or an `EdgeBatch`."""
    if graphs.dense_ok:
        return torch.from_numpy(graphs.dense()[graph_index].astype(np.float32)).to(device)
    return graphs.batch(graph_index, device)


def check_finished(pred: Predicted) -> None:
    """Raise `PredictionFailed` when some rollout did not finish or is not finite."""
    failed = np.flatnonzero((pred.status != 0)
                            | ~np.isfinite(pred.states).reshape(len(pred.states), -1).all(1))
    if len(failed):
        from mpnode_cli.solver import Status

        first = Status(int(pred.status[failed[0]])) if pred.status[failed[0]] else None
        why = f" ({first.name}: {first.message})" if first is not None else ""
        raise PredictionFailed(
            f"{len(failed)} of {len(pred.status)} rollouts did not finish (the first: "
            f"trajectory {int(failed[0])}{why}); their predictions are not finite, so no "
            "file was written")


def _names_memory_errors(step: str) -> Callable[[F], F]:
    """A decorator: a `MemoryError` inside the function (numpy's `_ArrayMemoryError`, with
    the shape it could not allocate) is raised again as "out of memory <step> (...)", so
    that the verb's one line says which step ran out."""

    def decorate(function: F) -> F:
        @functools.wraps(function)
        def named(*args: Any, **kwargs: Any) -> Any:
            try:
                return function(*args, **kwargs)
            except MemoryError as exc:
                raise MemoryError(f"out of memory {step} ({exc or 'no detail'})") from None

        return cast(F, named)

    return decorate


@_names_memory_errors("writing the predictions")
def write_predictions(path: str | Path, ckpt, pred: Predicted, *, time: np.ndarray,
                      graphs: Graphs, graph_index: np.ndarray, controls: np.ndarray | None = None,
                      split: np.ndarray | None = None, config: dict[str, Any],
                      source: dict[str, Any], dtype: str = "float32",
                      overwrite: bool = False, node_flags: np.ndarray | None = None) -> Path:
    """Write predictions as an `mpnode-dataset` file (see the module docstring).

    Args:
        path: the file (written atomically, `write_dataset`).
        ckpt: the checkpoint that predicted.
        pred: `roll_out`'s result.
        time: `[T]` sample times.
        graphs, graph_index: the graphs and `[K]` each trajectory's (only the graphs some
            trajectory ran on are stored).
        controls: `[K, T, N, U]` physical, or None.
        split: `[K]` split of each trajectory (default: all test, 2).
        config: the verb's resolved options, stored as the file's `config`.
        source: what the rollouts started from (JSON-able), stored in `prediction`.
        dtype: storage dtype of states, messages and controls.
        overwrite: replace an existing regular file.
        node_flags: uint8 `[K, N]` the nodes outside the training range, stored as
            `extrapolation` (`NodeExtrapolation.flags`), or None (not stored).

    Raises:
        PredictionFailed: some rollouts did not finish (nothing is written).
        MemoryError: "out of memory writing the predictions (...)" (nothing is written).
    """
    check_finished(pred)
    k = len(pred.states)
    used, graph_index = np.unique(np.asarray(graph_index), return_inverse=True)
    graphs = graphs.take(used)
    graph_index = graph_index.reshape(k).astype(np.int32)
    states = pred.states.astype(dtype)
    time = np.asarray(time, dtype=np.float64)
    record = {
        "checkpoint": str(Path(ckpt.path).resolve()) if ckpt.path else None,
        "checkpoint_sha256": file_sha256(ckpt.path) if ckpt.path else None,
        "checkpoint_epoch": ckpt.epoch,
        **({} if ckpt.member is None else {"member": ckpt.member}),
        "model_kind": ckpt.model_kind,
        "trained_on": {key: ckpt.dataset.get(key) for key in ("system", "fingerprint", "path",
                                                              "num_nodes")},
        "solver": rollout_solver(ckpt).model_dump(mode="json"),
        "source": source,
        "units": "states and controls physical; hidden/messages the model's own"
                 + ("; hidden/ensemble_std physical" if pred.spread is not None else ""),
    }
    hidden = {} if pred.messages is None else {"messages": pred.messages.astype(dtype)}
    if pred.spread is not None:
        hidden["ensemble_std"] = pred.spread.astype(dtype)
    dataset = Dataset(
        system=str(ckpt.dataset.get("system") or "custom"),
        dt=float(time[1] - time[0]),
        state_names=tuple(ckpt.dataset.get("state_names")
                          or (f"x{i}" for i in range(states.shape[-1]))),
        control_names=tuple(ckpt.dataset.get("control_names") or ()),
        periodic_states=tuple(ckpt.dataset.get("periodic_states") or ()),
        seed=None, config={**config, "solver": record["solver"]}, time=time, states=states,
        controls=None if controls is None else np.asarray(controls).astype(dtype),
        hidden=hidden, graphs=graphs, graph_index=graph_index,
        split=np.full(k, 2, dtype=np.uint8) if split is None else np.asarray(split, np.uint8),
        solver_status=pred.status, solver_n_f_evals=pred.n_f_evals,
        extrapolation=node_flags,
        extra_attrs={"prediction": json.dumps(record, sort_keys=True),
                     "fingerprint": fingerprint(states, graphs, graph_index, time,
                                                controls=controls)},
    )
    return write_dataset(path, dataset, overwrite=overwrite)
