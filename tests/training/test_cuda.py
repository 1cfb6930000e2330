"""The CUDA paths end to end: solver, model, train, evaluate, zeroshot and simulate on a GPU.

Each test runs the same work on the CPU and on the accelerator and compares the numbers,
so the reference is the CPU path, which the rest of the suite checks against scipy and
closed forms. Skipped cleanly where torch sees no CUDA device (CI has none).
`MPNODE_TEST_DEVICE=cpu` runs these tests with the CPU standing in for the GPU, to check the
tests themselves on a machine without one.
"""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch
from conftest import invoke

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.solver import solve

DEVICE = os.environ.get("MPNODE_TEST_DEVICE", "cuda")
pytestmark = pytest.mark.skipif(DEVICE == "cuda" and not torch.cuda.is_available(),
                                reason="torch sees no CUDA device")
NO_COMPILE = "[solver]\ncompile = false\n"


def lorenz_pair(y: torch.Tensor) -> torch.Tensor:
    """Two diffusively coupled Lorenz systems, `y [B, 2, 3]` (Lorenz 1963, σ 10, ρ 28, β 8/3)."""
    x, v, z = y[..., 0], y[..., 1], y[..., 2]
    f = torch.stack([10.0 * (v - x), x * (28.0 - z) - v, x * v - 8.0 / 3.0 * z], dim=-1)
    return f + 0.5 * (y.flip(1) - y)


def test_batched_solve_on_the_device_matches_the_cpu():
    y0 = torch.rand(512, 2, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    t = torch.linspace(0.0, 1.0, 21, dtype=torch.float64)
    cpu = solve(lambda _t, y: lorenz_pair(y), y0, t, rtol=1e-8, atol=1e-8)
    dev = solve(lambda _t, y: lorenz_pair(y), y0.to(DEVICE), t.to(DEVICE), rtol=1e-8,
                atol=1e-8)
    assert dev.ys.device.type == torch.device(DEVICE).type
    assert dev.ys.dtype == torch.float64
    assert bool((dev.status.cpu() == 0).all())
    # Both meet rtol 1e-8 on a chaotic flow for one time unit; rounding differs by device.
    np.testing.assert_allclose(dev.ys.cpu().numpy(), cpu.ys.numpy(), rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("cuda")
    paths = {n: generate(GenerateConfig(system="lorenz", nodes=n, trajectories=k, t_end=0.5,
                                        dt=0.05, out=root / f"l{n}.h5")).path
             for n, k in ((3, 32), (5, 8))}
    (root / "fast.toml").write_text(NO_COMPILE)
    return {"root": root, **paths}


def test_train_evaluate_zeroshot_and_simulate_on_the_device(data, tmp_path):
    run = tmp_path / "run"
    result = invoke("train", data[3], "--epochs", 2, "--batch-size", 8, "--no-plots",
                    "--device", DEVICE, "--config", data["root"] / "fast.toml",
                    "--run-dir", run)
    assert result.exit_code == 0, result.output
    summary = json.loads((run / "summary.json").read_text())
    assert np.isfinite(summary["min_val_mse"])
    best = run / "checkpoints" / "best.pt"

    # The same checkpoint evaluated on the device and on the CPU: the same MSE.
    on = {d: json.loads(invoke("evaluate", best, data[3], "--split", "validation", "--json",
                               "--device", d).output)["result"]["mse"]
          for d in (DEVICE, "cpu")}
    assert on[DEVICE] == pytest.approx(on["cpu"], rel=1e-4)
    assert on["cpu"] == pytest.approx(summary["min_val_mse"], rel=1e-4)

    result = invoke("zeroshot", best, data[5], "--device", DEVICE)
    assert result.exit_code == 0, result.output

    x0 = np.random.default_rng(0).uniform(-1, 1, size=(4, 5, 3))
    np.save(tmp_path / "x0.npy", x0)
    np.save(tmp_path / "g.npy", np.ones((5, 5), dtype=np.uint8) - np.eye(5, dtype=np.uint8))
    preds = {}
    for label, d in (("dev", DEVICE), ("cpu", "cpu")):
        out = tmp_path / f"pred-{label}.h5"
        result = invoke("simulate", run, "--x0", tmp_path / "x0.npy", "--adjacency",
                        tmp_path / "g.npy", "--t-end", 0.5, "--dt", 0.05, "--out", out,
                        "--device", d)
        assert result.exit_code == 0, result.output
        preds[label] = read_dataset(out).states
    np.testing.assert_allclose(preds["dev"], preds["cpu"], rtol=1e-4, atol=1e-4)


def test_resume_on_the_device_continues_a_cpu_run(data, tmp_path):
    run = tmp_path / "run"
    assert invoke("train", data[3], "--epochs", 1, "--batch-size", 8, "--no-plots",
                  "--config", data["root"] / "fast.toml", "--run-dir", run).exit_code == 0
    result = invoke("train", "--resume", run, "--epochs", 2, "--device", DEVICE)
    assert result.exit_code == 0, result.output
    metrics = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [m["epoch"] for m in metrics][-1] == 2
