"""The error-vs-time plot that evaluate (and train's plots) draws shows the two baselines its
table shows beside the model: hold x(0) and the train split's time mean, each checked
against numpy from the dataset file."""

from __future__ import annotations

import json

import h5py
import numpy as np
from conftest import invoke

import mpnode_cli.report.plots as plots
from mpnode_cli.training.checkpoint import load_checkpoint


def test_the_error_plot_draws_both_baselines(user_files, tmp_path, monkeypatch):
    drawn = {}
    real = plots.plot_error_vs_time

    def capture(time, curves, path, **options):
        drawn.update(curves=np.atleast_2d(np.asarray(curves, dtype=float)), **options)
        return real(time, curves, path, **options)

    monkeypatch.setattr(plots, "plot_error_vs_time", capture)
    result = invoke("evaluate", user_files["checkpoint"], user_files["data"], "--split", "all",
                    "--plot", "--plot-dir", tmp_path, "--json")
    assert result.exit_code == 0, result.output
    row = json.loads(result.output)
    assert (tmp_path / "data-all-error.png").is_file()

    # The reference, from the file: normalized states, the train split's mean per time.
    norm = load_checkpoint(user_files["checkpoint"]).build_normalizer()
    mean, std = norm.x_mean.double().numpy(), norm.x_std.double().numpy()
    with h5py.File(user_files["data"]) as f:
        x = (f["states"][()].astype(np.float64) - mean) / std  # (K, T, N, D)
        train = x[f["split"][()] == 0]
    hold = ((x - x[:, :1]) ** 2).mean(axis=(0, 2, 3))  # (T,)
    time_mean = ((x - train.mean(axis=(0, 2))[None, :, None]) ** 2).mean(axis=(0, 2, 3))

    model, *baselines = drawn["curves"]
    assert drawn["labels"] == ("model", *plots.BASELINE_LABELS)
    np.testing.assert_allclose(model, row["result"]["mse_vs_time"], rtol=1e-6)
    np.testing.assert_allclose(baselines[0], hold, rtol=1e-5, atol=1e-12)
    np.testing.assert_allclose(baselines[1], time_mean, rtol=1e-5)
    # The curves are the table's numbers, sample by sample: their mean over t₁.. is it.
    assert np.isclose(hold[1:].mean(), row["baselines"]["hold_x0"], rtol=1e-5)
    assert np.isclose(time_mean[1:].mean(), row["baselines"]["time_mean"], rtol=1e-5)
