"""`mpnode train --normalize asinh`: the z-score of asinh(x / s), against numpy's arcsinh
and median, its inverse, its first-order spread against finite differences, and a run
trained, saved and evaluated with it."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import invoke, one_line_error

from mpnode_cli.config import TrainConfig
from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.evaluate import evaluate, predict
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path


def _states() -> torch.Tensor:
    """`[K, T, N, 2]` float64: a component spanning four decades (a hub's beside typical
    nodes') and an angle-like one."""
    gen = torch.Generator().manual_seed(0)
    hubs = torch.logspace(-1, 3, 8, dtype=torch.float64)  # 0.1 … 1000, one per node
    x = hubs * (1 + 0.1 * torch.rand(5, 7, 8, generator=gen, dtype=torch.float64))
    angle = 3 * torch.randn(5, 7, 8, generator=gen, dtype=torch.float64)
    return torch.stack([x, angle], dim=-1)


def test_asinh_is_the_z_score_of_arcsinh_over_the_median():
    x = _states()
    norm = Normalizer.fit(x, asinh=True)
    s = np.quantile(np.abs(x.numpy().reshape(-1, 2)), 0.5, axis=0, method="lower")
    np.testing.assert_allclose(norm.x_scale.numpy(), s, rtol=1e-6)
    lifted = np.arcsinh(x.numpy() / s)
    mean, std = lifted.reshape(-1, 2).mean(0), lifted.reshape(-1, 2).std(0)
    np.testing.assert_allclose(norm.norm_x(x).numpy(), (lifted - mean) / std, rtol=1e-5,
                               atol=1e-6)
    # Four decades of the first component become a few units.
    assert float(norm.norm_x(x)[..., 0].abs().max()) < 3


def test_asinh_round_trips_and_leaves_an_unscaled_angle_linear():
    x = _states()
    norm = Normalizer.fit(x, asinh=True).unscaled([1])
    assert float(norm.x_scale[1]) == 0
    torch.testing.assert_close(norm.norm_x(x)[..., 1], x[..., 1])  # radians, as they were
    # float32 statistics, float64 states: exact to the float32 scale's rounding.
    torch.testing.assert_close(norm.denorm_x(norm.norm_x(x)), x, rtol=1e-5, atol=1e-9)


def test_the_spread_is_first_order_about_the_mean():
    x = _states()
    norm = Normalizer.fit(x, asinh=True)
    at = norm.norm_x(x)
    spread = torch.full_like(at, 1e-6)
    exact = (norm.denorm_x(at + spread) - norm.denorm_x(at - spread)) / 2
    torch.testing.assert_close(norm.denorm_spread(spread, at), exact, rtol=1e-6, atol=1e-12)
    with pytest.raises(ValueError, match="needs the states a spread is about"):
        norm.denorm_spread(spread)


def test_the_dict_round_trips_and_an_older_one_is_a_plain_z_score():
    x = _states()
    norm = Normalizer.fit(x, asinh=True)
    again = Normalizer.from_dict(norm.to_dict())
    torch.testing.assert_close(again.norm_x(x.float()), norm.norm_x(x.float()))
    plain = Normalizer.fit(x)
    assert "x_scale" not in plain.to_dict() and plain.x_scale is None
    old = Normalizer.from_dict({k: v for k, v in plain.to_dict().items()})
    torch.testing.assert_close(old.norm_x(x.float()), ((x - x.mean((0, 1, 2)))
                                                       / x.std((0, 1, 2), correction=0)).float())



def test_a_run_with_asinh_saves_it_and_errors_are_physical(gene_ba4, tmp_path):
    train(TrainConfig(dataset=gene_ba4, run_dir=tmp_path / "run", epochs=2, seed=0,
                      normalize="asinh", model_options={"hidden": 8}))
    ckpt = load_checkpoint(checkpoint_path(tmp_path / "run", "best"))
    data = TrajectoryData.load(gene_ba4).subset("all")
    norm = ckpt.build_normalizer()
    train_states = TrajectoryData.load(gene_ba4).subset("train").states.double()
    np.testing.assert_allclose(norm.x_scale.numpy(),
                               np.quantile(np.abs(train_states.numpy()).reshape(-1, 1), 0.5,
                                           axis=0, method="lower"),
                               rtol=1e-6)
    model = ckpt.build_model()
    result = evaluate(model, data, norm, batch_size=8)
    pred = predict(model, data, norm, torch.arange(len(data)))
    phys = (pred.pred - pred.true)[:, 1:].double()
    assert result.rmse == pytest.approx(phys.pow(2).mean(dim=(0, 1, 2)).sqrt().tolist(),
                                        rel=1e-5)


def test_asinh_with_stream_is_one_line(gene_ba4, tmp_path):
    line = one_line_error(invoke("train", gene_ba4, "--normalize", "asinh", "--stream",
                                 "--run-dir", tmp_path / "r"))
    assert "normalize asinh" in line and "--stream" in line
