"""A model's errors by in-degree (`evaluate --by-degree`): where on a graph it is wrong.

A node model sums (or averages) over a node's senders, so its error may grow with the
in-degree, and a hub may be far outside the degrees it was trained on
(`mpnode_cli.training.extrapolation`). The nodes are binned by in-degree, log-spaced as
bench/transfer.py bins its per-degree tables: [0, 1) for isolated nodes, then [1, 2),
[2, 4), [4, 8), ... (powers of two, so bins line up across graphs). The in-degree counts
an edge of multiplicity w w times (`Graphs.in_degree`).

Per bin, in physical units, as bench/transfer.py scores: the model's MSE over the bin's
node-trajectories whose rollout succeeded, their predicted samples (t₀ excluded) and
components; the two naive predictors' (`mpnode_cli.training.baselines`) over all of the
bin's node-trajectories, the time mean being the train split's physical mean at each
sample time; and the skill, MSE ÷ time-mean MSE. The sums are taken batch by batch as
`evaluate` rolls out (`DegreeSums.add`), so no prediction is kept.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.jsonable import jsonable
from mpnode_cli.report.members import shown
from mpnode_cli.training.baselines import time_mean_prediction
from mpnode_cli.training.extrapolation_nodes import NodeExtrapolation
from mpnode_cli.training.losses import Angles, difference


def degree_bin(degree: np.ndarray) -> np.ndarray:
    """int64 bin of each in-degree (an int array): 0 for [0, 1), b ≥ 1 for
    [2^(b−1), 2^b) (the binary exponent of d, exact for any int64 degree)."""
    return np.frexp(np.asarray(degree, dtype=np.float64))[1].astype(np.int64)


def bin_bounds(b: int) -> tuple[int, int]:
    """Bin b's in-degrees `[lo, hi)`."""
    return (0, 1) if b == 0 else (2 ** (b - 1), 2 ** b)


class DegreeSums:
    """Per-bin error sums over a split's batches (`evaluate`'s `per_batch`), and the
    rows they give (`rows`).

    Args:
        degree: int `[G, N]` the split's graphs' in-degrees (`Graphs.in_degree`).
        time: `[T]` the sample times. normalizer: the model's normalization.
        train: the train split(s) whose physical time mean is the time_mean predictor
            (`train_reference`'s).
        angles: components compared mod 2π (`checkpoint_angles`; normalized units, as
            `evaluate` takes them), or None.
    """

    def __init__(self, degree: np.ndarray, time: torch.Tensor, normalizer: Normalizer,
                 train: TrajectoryData | Sequence[TrajectoryData],
                 angles: Angles | None = None):
        d = normalizer.x_mean.numel()
        self.bins = degree_bin(degree)  # (G, N)
        self.size = int(self.bins.max()) + 1 if self.bins.size else 1
        self.values = max(time.numel() - 1, 0) * d  # predicted values per node-trajectory
        self.normalizer, self.angles = normalizer, angles
        physical = Normalizer(torch.zeros(d), torch.ones(d), torch.zeros(0), torch.zeros(0))
        self.time_mean = time_mean_prediction(train, time, physical)  # (T, D) or None
        keys = ("nodes", "failed", "mse", "mse_normalized", "time_mean", "hold_x0")
        self.sums = {key: np.zeros(self.size) for key in keys}
        self.members: list[dict[str, np.ndarray]] = []  # each member's, from the first batch

    def add(self, batch: TrajectoryData, x: torch.Tensor, out: Any, good: torch.Tensor) -> None:
        """One batch as `evaluate` rolls it out: `batch` its trajectories (physical),
        `x: [B, T, N, D]` their states normalized, `out` the rollout (`states`, and each
        member's, `members` and `member_status`), `good: [B]` bool (CPU) the rollouts that
        succeeded."""
        bins = self.bins[batch.graph_index.numpy()]  # (B, N)
        ok = good.numpy()
        self._add("nodes", bins, np.ones(bins.shape))
        self._add("failed", bins[~ok], np.ones(bins[~ok].shape))
        true = batch.states.double()  # (B, T, N, D)
        physical = None if self.angles is None else self.angles.physical()
        self._add("hold_x0", bins, _node_sq(true[:, :1], true, physical))
        if self.time_mean is not None:
            self._add("time_mean", bins, _node_sq(self.time_mean[None, :, None, :], true,
                                                  physical))
        if ok.any():
            keep = good.to(x.device)
            self._add("mse_normalized", bins[ok], _node_sq(out.states[keep], x[keep],
                                                           self.angles))
            self._add("mse", bins[ok], self._physical_sq(out.states[keep], x[keep]))
        self.members = self.members or [{"nodes": np.zeros(self.size),
                                         "mse": np.zeros(self.size)} for _ in out.members]
        for sums, pred, status in zip(self.members, out.members, out.member_status,
                                      strict=True):
            ok_k = ((status == 0).cpu() & torch.isfinite(pred).flatten(1).all(1).cpu()).numpy()
            if ok_k.any():
                keep = torch.from_numpy(ok_k).to(x.device)
                _bincount_into(sums["nodes"], bins[ok_k], np.ones(bins[ok_k].shape))
                _bincount_into(sums["mse"], bins[ok_k], self._physical_sq(pred[keep], x[keep]))

    def rows(self, nodes: NodeExtrapolation | None = None) -> list[dict[str, Any]]:
        """JSON-able, one per bin that holds a node-trajectory, in order of in-degree:
        lo, hi (its in-degrees `[lo, hi)`), node_trajectories, failed (of those, in
        rollouts that failed), mse (physical), mse_normalized (the training
        normalization's units, as `EvalResult.mse`), time_mean and hold_x0 (physical),
        skill (mse ÷ time_mean), states_outside (the share of the node-trajectories whose
        true states leave the training range at some sample, from `nodes`; None without
        it) and, for an ensemble, members_mean and members_std (the members' own MSE,
        physical, population std over the members)."""
        share = None
        if nodes is not None and nodes.how_far is not None:
            flat = degree_bin(nodes.in_degree).ravel()  # (K·N,)
            outside = np.bincount(flat, weights=nodes.state_outside.ravel().astype(float),
                                  minlength=self.size)
            share = outside / np.maximum(np.bincount(flat, minlength=self.size), 1)
        s, rows = self.sums, []
        for b in np.flatnonzero(s["nodes"]):
            scored = (s["nodes"][b] - s["failed"][b]) * self.values
            everyone = s["nodes"][b] * self.values
            lo, hi = bin_bounds(int(b))
            row = {"lo": lo, "hi": hi, "node_trajectories": int(s["nodes"][b]),
                   "failed": int(s["failed"][b]),
                   "mse": _ratio(s["mse"][b], scored),
                   "mse_normalized": _ratio(s["mse_normalized"][b], scored),
                   "time_mean": _ratio(s["time_mean"][b], everyone)
                   if self.time_mean is not None else None,
                   "hold_x0": _ratio(s["hold_x0"][b], everyone)}
            row["skill"] = (row["mse"] / row["time_mean"]
                            if row["time_mean"] and row["mse"] is not None else None)
            row["states_outside"] = None if share is None else float(share[b])
            each = np.array([m["mse"][b] / (m["nodes"][b] * self.values)
                             if m["nodes"][b] * self.values else np.nan for m in self.members])
            row |= shown(len(each), {"members_mean": float(each.mean()),
                                     "members_std": float(each.std())}) or {}
            rows.append(jsonable(row))
        return rows

    def _add(self, key: str, bins: np.ndarray, values: np.ndarray) -> None:
        _bincount_into(self.sums[key], bins, values)

    def _physical_sq(self, pred: torch.Tensor, x: torch.Tensor) -> np.ndarray:
        """`[B, N]` Σ squared physical error of normalized `pred, x: [B, T, N, D]`, as
        `evaluate`'s RMSE takes it (both mapped back by the normalization)."""
        denorm = self.normalizer.denorm_x
        return _node_sq(denorm(pred), denorm(x),
                        None if self.angles is None else self.angles.physical())


def degree_sums(data: TrajectoryData, subset: TrajectoryData, normalizer: Normalizer,
                train: TrajectoryData | Sequence[TrajectoryData],
                angles: Angles | None = None) -> DegreeSums:
    """The `DegreeSums` of a split `subset` of `data` (`evaluate_checkpoint`'s).

    Raises:
        ValueError: `data` holds a model's predictions, not ground truth.
    """
    if data.attrs.get("prediction"):
        raise ValueError(f"{data.path.name} holds a model's predictions, not ground truth: "
                         "errors by in-degree need a dataset of true states")
    return DegreeSums(subset.graphs.in_degree(), subset.time, normalizer, train, angles)


def _node_sq(pred: torch.Tensor, true: torch.Tensor, angles: Angles | None) -> np.ndarray:
    """float64 `[B, N]`: each node-trajectory's Σ of squared errors over t₁.. and the
    components (`pred` broadcast against `true: [B, T, N, D]`)."""
    pred = pred.expand_as(true)
    return difference(pred[:, 1:], true[:, 1:], angles).pow(2).double().sum(dim=(1, 3)).cpu(
    ).numpy()


def _bincount_into(total: np.ndarray, bins: np.ndarray, values: np.ndarray) -> None:
    """Add `values` into `total` at their `bins` (same shape)."""
    total += np.bincount(bins.ravel(), weights=values.ravel(), minlength=len(total))


def _ratio(total: float, count: float) -> float | None:
    return float(total / count) if count else None
