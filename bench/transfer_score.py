"""Scoring for `bench/transfer.py`: a model's errors on a target's test split in physical
units, beside the target's own naive predictors, per node and by in-degree.

`score` runs in a worker process (`bench/transfer.py --score`, one torch thread); the rest
is numpy, shared with the table and the tests.
"""

from __future__ import annotations

import base64
import math
import zlib
from pathlib import Path
from typing import Any

import numpy as np

# Per-node arrays kept in a record: name → storage dtype.
PER_NODE = {"degree": "int32", "mse": "float32", "time_mean": "float32", "outside": "float16"}


def pack(values: np.ndarray, dtype: str) -> str:
    """A 1-D array as compressed base64 text (`unpack` reads it back)."""
    raw = np.ascontiguousarray(values, dtype=dtype).tobytes()
    return base64.b64encode(zlib.compress(raw, 9)).decode("ascii")


def unpack(text: str, dtype: str) -> np.ndarray:
    return np.frombuffer(zlib.decompress(base64.b64decode(text)), dtype=dtype)


def degree_bins(degree: np.ndarray) -> list[tuple[int, int]]:
    """Log-spaced bins [lo, hi) of in-degree covering `degree`: [0, 1), [1, 2), [2, 4),
    [4, 8), ... (powers of two, so bins line up across targets and seeds)."""
    top = int(np.max(degree)) if degree.size else 0
    bins = [(0, 1)] if degree.size and int(np.min(degree)) == 0 else []
    lo = 1
    while lo <= top:
        bins.append((lo, 2 * lo))
        lo *= 2
    return bins


def by_degree(per_node: dict[str, np.ndarray]) -> list[dict[str, Any]]:
    """Per-bin means of the per-node arrays (`degree`, `mse`, `time_mean`, `outside`; a
    node-trajectory whose rollout failed has mse NaN and is left out of that bin's MSE)."""
    degree = np.asarray(per_node["degree"])
    rows = []
    for lo, hi in degree_bins(degree):
        mask = (degree >= lo) & (degree < hi)
        if not mask.any():
            continue
        row: dict[str, Any] = {"lo": lo, "hi": hi, "nodes": int(mask.sum())}
        for key in ("mse", "time_mean", "outside"):
            if key in per_node:
                part = np.asarray(per_node[key], dtype=np.float64)[mask]
                finite = part[np.isfinite(part)]
                row[key] = float(finite.mean()) if finite.size else None
        rows.append(row)
    return rows


def difference(pred: np.ndarray, true: np.ndarray, angles: tuple[int, ...] = ()) -> np.ndarray:
    """`pred − true` `[..., D]`, with the components `angles` (radians) wrapped: mpnode's
    own `losses.difference`, the one every loss and error takes, on float64 arrays."""
    if not angles:
        return pred - true
    import torch

    from mpnode_cli.training.losses import Angles
    from mpnode_cli.training.losses import difference as wrapped

    return wrapped(torch.from_numpy(np.ascontiguousarray(pred, dtype=np.float64)),
                   torch.from_numpy(np.ascontiguousarray(true, dtype=np.float64)),
                   Angles(tuple(angles))).numpy()


def node_mse(pred: np.ndarray, true: np.ndarray, angles: tuple[int, ...] = ()) -> np.ndarray:
    """`[K, N]`: each node-trajectory's MSE over its predicted samples (t₀ excluded) and
    components, physical units; `pred, true: [K, T, N, D]`; `angles` as `difference`."""
    return (difference(pred[:, 1:], true[:, 1:], angles) ** 2).mean(axis=(1, 3))


def time_mean_per_node(train: np.ndarray, test: np.ndarray,
                       angles: tuple[int, ...] = ()) -> np.ndarray:
    """`[K, N]`: the time-mean predictor's MSE per test node-trajectory, physical units.

    The predictor is `mpnode_cli.training.evaluate.baseline_mse`'s (x̂(t_k) = the mean of
    the train split's states at t_k over trajectories and nodes, per component); train and
    test of one dataset share the sample grid, so t_k matches sample by sample. `score`
    checks that the mean of this equals `baseline_mse`'s number. `angles` as
    `difference` (the predictor is still the plain mean, as `baseline_mse` takes it)."""
    mean_t = train.mean(axis=(0, 2))  # (T, D)
    diff = difference(np.broadcast_to(mean_t[None, 1:, None, :], test[:, 1:].shape),
                      test[:, 1:], angles)
    return (diff ** 2).mean(axis=(1, 3))


def outside_share(states: np.ndarray, train_range: list[list[float]]) -> np.ndarray:
    """`[K, N]`: the share of each node-trajectory's values (all samples and components)
    outside the per-component [min, max] a model was trained on."""
    lo, hi = np.asarray(train_range, dtype=np.float64).T  # (D,), (D,)
    return ((states < lo) | (states > hi)).mean(axis=(1, 3))


def _identity(d: int):
    import torch

    from mpnode_cli.data.dataset import Normalizer

    return Normalizer(torch.zeros(d), torch.ones(d), torch.zeros(0), torch.zeros(0))


def score(checkpoint: Path, dataset: Path, range_from: Path | None = None) -> dict[str, Any]:
    """A checkpoint's errors on a dataset's test split, all in physical units.

    Predictions come from `roll_out` (the checkpoint's normalization and solver); the
    time-mean and hold-x(0) predictors from `baseline_mse` with the dataset's own train
    split and an identity normalization (physical units). `skill` is MSE ÷ time-mean MSE.

    Args:
        range_from: the checkpoint whose training range `outside` is measured against
            (default: `checkpoint`'s own).
    """
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.evaluate import baseline_mse
    from mpnode_cli.training.losses import run_angles
    from mpnode_cli.training.predict import roll_out

    ckpt, data = load_checkpoint(checkpoint), TrajectoryData.load(dataset)
    train, test = data.subset("train"), data.subset("test")
    x = test.states.double().numpy()  # (K, T, N, D)
    controls = None if test.controls is None else test.controls.numpy()
    pred = roll_out(ckpt, x[:, 0], test.time.numpy(), test.graphs, test.graph_index.numpy(),
                    controls)
    ok = (pred.status == 0) & np.isfinite(pred.states).reshape(len(x), -1).all(axis=1)
    # A checkpoint trained with `--wrap-angles` is scored as it was trained: its dataset's
    # periodic states mod 2π, in its errors and the baselines' alike.
    angles = run_angles(bool(ckpt.train_config.get("wrap_angles")), ckpt.dataset, None)
    dims = angles.dims if angles else ()
    mse = node_mse(np.where(ok[:, None, None, None], pred.states, np.nan), x, dims)  # (K, N)
    base = baseline_mse(train, test, _identity(x.shape[-1]), angles)
    tm = time_mean_per_node(train.states.double().numpy(), x, dims)
    if not math.isclose(float(tm.mean()), base["time_mean"], rel_tol=1e-6, abs_tol=1e-12):
        raise AssertionError(f"time mean per node {tm.mean()} != baseline_mse "
                             f"{base['time_mean']}")
    reference = load_checkpoint(range_from) if range_from else ckpt
    train_range = reference.dataset["train_range"]
    outside = outside_share(x, train_range["states"])
    degree = np.asarray(test.graphs.in_degree())[test.graph_index.numpy()]  # (K, N)
    per_node = {"degree": degree.ravel(), "mse": mse.ravel(), "time_mean": tm.ravel(),
                "outside": outside.ravel()}
    value = float(np.nanmean(mse)) if ok.any() else None
    return {"dataset": Path(dataset).name, "trajectories": len(x), "nodes": x.shape[2],
            "failed": int((~ok).sum()), "mse": value, "time_mean": base["time_mean"],
            "wrapped": list(dims),
            "hold_x0": base["hold_x0"],
            "skill": value / base["time_mean"] if value is not None else None,
            "states_outside": float(outside.mean()),
            "in_degree": [int(degree.min()), int(degree.max())],
            "train_in_degree": train_range.get("in_degree"),
            "by_degree": by_degree(per_node),
            "per_node": {k: pack(v, PER_NODE[k]) for k, v in per_node.items()}}


def unpack_nodes(result: dict[str, Any]) -> dict[str, np.ndarray] | None:
    """A score's per-node arrays, or None where the record was stripped of them."""
    packed = result.get("per_node")
    if not packed:
        return None
    return {k: unpack(v, PER_NODE[k]) for k, v in packed.items()}


def in_range_report(checkpoint: Path, dataset: Path) -> dict[str, Any]:
    """Split a zero-shot error by whether a node's true states stay in the training range
    (`bench/transfer.py --in-range`; normalized units, t₀ excluded, every trajectory).

    A node whose states leave the range its model was trained on asks the model for its
    own dynamics where it has none; its error says nothing about the coupling's transfer.
    Returns the share of state values outside, and the MSE over the nodes that stay inside
    and over those that leave, with their counts.
    """
    from mpnode_cli.data.dataset import TrajectoryData
    from mpnode_cli.training.checkpoint import load_checkpoint
    from mpnode_cli.training.predict import roll_out

    ckpt, data = load_checkpoint(checkpoint), TrajectoryData.load(dataset)
    x = data.states.double().numpy()  # (K, T, N, D)
    controls = None if data.controls is None else data.controls.numpy()
    pred = roll_out(ckpt, x[:, 0], data.time.numpy(), data.graphs, data.graph_index.numpy(),
                    controls)
    std = ckpt.build_normalizer().x_std.double().numpy()  # (D,)
    err = ((pred.states[:, 1:] - x[:, 1:]) / std) ** 2  # (K, T-1, N, D)
    lo, hi = np.asarray(ckpt.dataset["train_range"]["states"]).T  # (D,), (D,)
    outside = (x < lo) | (x > hi)  # (K, T, N, D)
    node_out = outside.any(axis=(1, 3))  # (K, N): leaves the range at some time
    per_node = err.mean(axis=(1, 3))  # (K, N)
    degree = np.asarray(data.graphs.in_degree())[data.graph_index.numpy()]  # (K, N)
    return {"dataset": dataset.name, "states_outside": float(outside.mean()),
            "mse": float(per_node.mean()),
            "in_range_mse": float(per_node[~node_out].mean()) if (~node_out).any() else None,
            "in_range_nodes": int((~node_out).sum()),
            "out_of_range_mse": float(per_node[node_out].mean()) if node_out.any() else None,
            "out_of_range_nodes": int(node_out.sum()),
            "in_degree": [int(degree.min()), int(degree.max())],
            "train_in_degree": ckpt.dataset["train_range"]["in_degree"]}
