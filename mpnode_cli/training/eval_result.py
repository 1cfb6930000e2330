"""What an evaluation returns (`EvalResult`), an ensemble's members' summary of it, and
several datasets' results pooled into one, each weighted by its predicted values.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import torch

from mpnode_cli.jsonable import jsonable


@dataclass
class EvalResult:
    """Errors over the trajectories whose rollout succeeded.

    Attributes:
        trajectories: K evaluated. failed: rollouts the solver could not finish (excluded
            from the errors below; their count says whether the numbers can be trusted).
        mse: mean squared error in normalized units over all predicted samples.
        huber: the training loss "Huber along time" (δ = 1, summed over time and
            features, mean over trajectories × nodes), normalized units.
        node_mse: the training loss "node-mse" (each squared error over its node's
            variance along the trajectory), mean over every predicted value; NaN in
            results written before it existed.
        rmse: `[D]` root mean squared error per state in physical units.
        mse_vs_time: `[T]` normalized MSE at each sample time (0 at t₀), over trajectories,
            nodes and features.
        n_f_evals: right-hand-side evaluations, summed over batches (max within a batch).
        seconds: wall time of the rollouts.
        members: an ensemble's: each member's own result (the fields above are then the
            members' mean prediction's). None for a single model.
        spread: an ensemble's mean spread, the members' standard deviation over every
            predicted value (normalized units). None for a single model.
        spread_error_corr: an ensemble's Pearson correlation over trajectories between
            the spread and the mean prediction's RMSE (normalized): how well the spread
            ranks where the model is wrong. None for a single model.
    """

    trajectories: int
    failed: int
    mse: float
    huber: float
    rmse: list[float]
    mse_vs_time: list[float]
    n_f_evals: int
    seconds: float
    members: list[EvalResult] | None = None
    spread: float | None = None
    spread_error_corr: float | None = None
    node_mse: float = math.nan

    def loss(self, name: str) -> float:
        """The error a training loss name selects (`mpnode_cli.training.losses.LOSSES`);
        inf if any failed."""
        if self.failed:
            return math.inf
        return {"huber": self.huber, "mse": self.mse, "node-mse": self.node_mse}[name]

    def to_dict(self) -> dict[str, Any]:
        """JSON-able, with non-finite numbers as None; an ensemble's with `members_mean`
        and `members_std`, each member's MSE and RMSE over the members."""
        out = jsonable(asdict(self))
        if self.members:
            out |= jsonable(member_stats(self.members))
        return out


def member_stats(members: Sequence[EvalResult]) -> dict[str, Any]:
    """An ensemble's members' errors as mean ± std (population) over the members:
    `{"members_mean": {"mse", "rmse"}, "members_std": {"mse", "rmse"}}`."""
    mse = torch.tensor([m.mse for m in members], dtype=torch.float64)
    rmse = torch.tensor([m.rmse for m in members], dtype=torch.float64)
    return {"members_mean": {"mse": float(mse.mean()), "rmse": rmse.mean(0).tolist()},
            "members_std": {"mse": float(mse.std(correction=0)),
                            "rmse": rmse.std(0, correction=0).tolist()}}


def pooled(results: Sequence[EvalResult], nodes: Sequence[int],
           scale: Sequence[float] | None = None) -> EvalResult:
    """Several datasets' results as one: the numbers `evaluate` would give if their
    trajectories were one split (each mean is over every value of every dataset).

    The MSE and the node-scaled MSE are element-weighted: each dataset's counts by its
    predicted values,
    ok · (T − 1) · N · D (ok: its trajectories whose rollout succeeded); the RMSE per state
    likewise by ok · (T − 1) · N; the Huber loss (a mean over trajectories × nodes) by
    ok · N; `mse_vs_time[k]` by ok · N over the datasets that have a k-th sample (their
    sample times share one grid, `mpnode_cli.data.pooled.check_poolable`). Counts and RHS
    evaluations are summed.

    Args:
        results: one per dataset. nodes: N of each dataset.
        scale: a factor on each dataset's weights (`--balance-datasets`: 1 / its states'
            variance); None: 1 for each.

    Returns:
        The pooled result; the result itself when there is one.
    """
    if len(results) == 1:
        return results[0]
    ok = [r.trajectories - r.failed for r in results]
    if scale is not None:
        ok = [o * w for o, w in zip(ok, scale, strict=True)]
    samples = [len(r.mse_vs_time) for r in results]
    values = [o * (t - 1) * n for o, t, n in zip(ok, samples, nodes, strict=True)]
    node_rows = [o * n for o, n in zip(ok, nodes, strict=True)]
    rmse = [math.sqrt(_weighted([r.rmse[j] ** 2 for r in results], values))
            for j in range(len(results[0].rmse))]
    per_time = [_weighted([r.mse_vs_time[k] if k < t else 0.0
                           for r, t in zip(results, samples, strict=True)],
                          [w if k < t else 0 for w, t in zip(node_rows, samples, strict=True)])
                for k in range(max(samples))]
    return EvalResult(
        trajectories=sum(r.trajectories for r in results),
        failed=sum(r.failed for r in results),
        mse=_weighted([r.mse for r in results], values),
        huber=_weighted([r.huber for r in results], node_rows),
        node_mse=_weighted([r.node_mse for r in results], values),
        rmse=rmse, mse_vs_time=per_time, n_f_evals=sum(r.n_f_evals for r in results),
        seconds=sum(r.seconds for r in results),
    )  # fmt: skip


def pooled_baselines(baselines: Sequence[dict[str, float | None]],
                     weights: Sequence[int]) -> dict[str, float | None]:
    """Several datasets' `baseline_mse` as one, each weighted by its predicted values
    K · (T − 1) · N · D (`mpnode_cli.data.pooled.element_weights`), as `pooled` weights
    the model's MSE; None where any dataset's is undefined."""
    out: dict[str, float | None] = {}
    for key in baselines[0]:
        values = [b.get(key) for b in baselines]
        out[key] = None if any(v is None or not math.isfinite(v) for v in values) else (
            _weighted(values, weights))
    return out


def _weighted(values: Sequence[float], weights: Sequence[float]) -> float:
    """Σ w·v / Σ w over the values of nonzero weight (NaN when none has one)."""
    total = sum(weights)
    if not total:
        return math.nan
    return sum(v * w for v, w in zip(values, weights, strict=True) if w) / total


def by_dataset(names: Sequence[str], each: Sequence[EvalResult], loss: str) -> dict[str, Any]:
    """A metrics row's per-dataset validation values (none for one dataset, whose row keeps
    the keys it always had); `loss` is the training loss's name."""
    if len(each) == 1:
        return {}
    pairs = list(zip(names, each, strict=True))
    return {"val_loss_by_dataset": {n: r.loss(loss) for n, r in pairs},
            "val_mse_by_dataset": {n: r.mse for n, r in pairs},
            "val_failed_by_dataset": {n: r.failed for n, r in pairs}}
