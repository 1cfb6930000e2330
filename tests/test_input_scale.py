"""MP-NODE's `input_scale="asinh"`: robust statistics fitted on the train states, the
features the MLPs see against a closed form, the linear path on the unscaled states, and a
trained checkpoint that keeps its statistics."""

from __future__ import annotations

import numpy as np
import torch

from mpnode_cli.config import TrainConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.models.mpnode import MPNODE
from mpnode_cli.models.options import MPNODEOptions
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.loop import train
from mpnode_cli.training.run import checkpoint_path


def _lower_median(a: np.ndarray) -> np.ndarray:
    return np.quantile(a, 0.5, axis=0, method="lower")


def _model(**options) -> MPNODE:
    torch.manual_seed(0)
    return MPNODE(2, options=MPNODEOptions(input_scale="asinh", update="affine",
                                           aggregate="sum", **options)).double()


def _states() -> torch.Tensor:
    """`[K, T, N, 2]`: typical nodes near 1 and hubs near 100 (one component), and a
    second component on another scale."""
    gen = torch.Generator().manual_seed(1)
    base = torch.rand(4, 6, 9, 2, generator=gen, dtype=torch.float64)
    base[:, :, :2, 0] *= 100.0  # two hubs
    base[..., 1] = 5 + 0.01 * base[..., 1]
    return base


def test_the_statistics_are_the_median_and_its_absolute_deviation():
    model, x = _model(), _states()
    model.fit_statistics(x, 0.1, torch.ones(4, 9, 9))
    flat = x.reshape(-1, 2).numpy()
    center = _lower_median(flat)
    np.testing.assert_allclose(model.input_center.numpy(), center, rtol=1e-12)
    np.testing.assert_allclose(model.input_spread.numpy(),
                               _lower_median(np.abs(flat - center)), rtol=1e-12)
    feats = model.features(x)
    np.testing.assert_allclose(feats.numpy(), np.arcsinh((x.numpy() - model.input_center.numpy())
                                                         / model.input_spread.numpy()),
                               rtol=1e-12)
    # A hub 100× a typical node lies a few units out, not ~100 spreads.
    assert float(feats[..., 0].abs().max()) < 7
    before = model.input_spread.clone()
    model.fit_statistics(x * 3, 0.1, torch.ones(4, 9, 9))  # fitted once: a finetune keeps it
    torch.testing.assert_close(model.input_spread, before)


def test_the_mlp_sees_the_features_and_the_linear_path_the_states():
    model = _model(linear_path=True, messages=False)
    x = _states()
    model.fit_statistics(x, 0.1, torch.ones(4, 9, 9))
    with torch.no_grad():
        model.net.linear_weight.normal_()
    z = torch.cat([x[:, 0], torch.zeros(4, 9, model.message_dim, dtype=x.dtype)], dim=-1)
    field = model.vector_field(torch.ones(4, 9, 9, dtype=x.dtype))(torch.zeros(4), z)
    plain_mlp = torch.nn.Sequential(*list(model.net))  # the same layers, no linear path
    out = plain_mlp(model.features(x[:, 0])) + x[:, 0] @ model.net.linear_weight.T
    d, m = 2, model.message_dim
    torch.testing.assert_close(field, out[..., :d + m], rtol=1e-12, atol=1e-12)  # G · 0 = 0



def test_a_trained_checkpoint_keeps_its_statistics(gene_ba4, tmp_path):
    train(TrainConfig(dataset=gene_ba4, run_dir=tmp_path / "run", epochs=2, seed=0,
                      model_options={"hidden": 8, "input_scale": "asinh",
                                     "linear_path": True}))
    ckpt = load_checkpoint(checkpoint_path(tmp_path / "run", "best"))
    model, norm = ckpt.build_model(), ckpt.build_normalizer()
    z = norm.norm_x(TrajectoryData.load(gene_ba4).subset("train").states).double().reshape(-1, 1)
    center = _lower_median(z.numpy())
    np.testing.assert_allclose(model.input_center.double().numpy(), center, rtol=1e-6)
    np.testing.assert_allclose(model.input_spread.double().numpy(),
                               _lower_median(np.abs(z.numpy() - center)), rtol=1e-5)
