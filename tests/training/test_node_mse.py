"""The node-scaled loss (`--loss node-mse`): a closed form, its scale invariance, and a
run trained and validated on it."""

from __future__ import annotations

import math

import pytest
import torch

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.training.loop import train
from mpnode_cli.training.losses import NODE_VARIANCE_FLOOR, mse_loss, node_mse_loss
from mpnode_cli.training.run import read_metrics


def test_node_mse_is_each_error_over_its_nodes_variance():
    t = torch.linspace(0, 1, 11, dtype=torch.float64)
    # Two nodes: a ramp over [0, 1] (its variance in closed form below), and a node at
    # rest, which weighs by the floor alone.
    target = torch.stack([t, torch.full_like(t, 3.0)], dim=-1)[None, :, :, None]  # [1,T,2,1]
    pred = target + torch.tensor([0.1, 0.2], dtype=torch.float64)[None, None, :, None]
    ramp_variance = float(((t - t.mean()) ** 2).mean())  # (T² − 1)/(12 (T − 1)²), T = 11
    assert ramp_variance == pytest.approx((11**2 - 1) / (12 * 10**2))
    expected = (0.1**2 / (ramp_variance + NODE_VARIANCE_FLOOR)
                + 0.2**2 / NODE_VARIANCE_FLOOR) / 2
    assert float(node_mse_loss(pred, target)) == pytest.approx(expected, rel=1e-12)


def test_a_node_scaled_up_counts_as_before_where_mse_counts_it_squared():
    gen = torch.Generator().manual_seed(0)
    target = torch.randn(3, 9, 5, 2, generator=gen, dtype=torch.float64)
    pred = target + 0.1 * torch.randn(target.shape, generator=gen, dtype=torch.float64)
    hub = torch.ones(5, 1, dtype=torch.float64)
    hub[2] = 1000.0  # node 2's trajectory and its error 1000× larger: a hub
    before = float(node_mse_loss(pred, target))
    after = float(node_mse_loss(pred * hub, target * hub))
    variance = target.var(dim=1, correction=0)
    # Only the floor's share of node 2 changes: bounded by the floor over its variance.
    assert after == pytest.approx(before, rel=float(NODE_VARIANCE_FLOOR / variance.min()))
    assert float(mse_loss(pred * hub, target * hub)) > 1e4 * float(mse_loss(pred, target))



def test_a_run_trains_and_selects_on_node_mse(gene_ba4, tmp_path):
    summary = train(TrainConfig(dataset=gene_ba4, run_dir=tmp_path / "run", epochs=3, seed=0,
                                loss="node-mse", model_options={"hidden": 8}))
    rows = [r for r in read_metrics(tmp_path / "run") if r["epoch"] > 0]
    assert all(math.isfinite(r["train_loss"]) for r in rows)
    # The validation loss is the node-scaled one, not the MSE, and the best epoch is its
    # minimum.
    assert all(r["val_loss"] != pytest.approx(r["val_mse"]) for r in rows)
    best = min(read_metrics(tmp_path / "run"), key=lambda r: r["val_loss"])
    assert summary.min_val_loss == pytest.approx(best["val_loss"])
    assert summary.test["node_mse"] is not None and summary.test["node_mse"] > 0
