"""What a user of an ensemble checkpoint (`train --seeds S`) gets: evaluate's members' mean
± std and spread, simulate's `hidden/ensemble_std`, `--member K` and the exported member.

Every number is checked against the members rolled out one by one as single models (each
built from its own exported checkpoint) and numpy's mean, std and corrcoef over them. The
ensemble is trained in float64: its members run through stacked weights and the references
through plain ones, whose float32 round-off differs enough to flip an adaptive step's
accept or reject now and then, after which two solves differ by about the solver's tolerance
(1e-4), not by round-off.
"""

from __future__ import annotations

import json
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import torch
from conftest import invoke

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.simulate import SimulateConfig
from mpnode_cli.config.train import TrainConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.models.ensemble import spread_error_correlation
from mpnode_cli.report.tables import fmt
from mpnode_cli.training.checkpoint import load_checkpoint
from mpnode_cli.training.checkpoint_members import member_checkpoint
from mpnode_cli.training.checkpoint_report import evaluate_checkpoint
from mpnode_cli.training.loop import train
from mpnode_cli.training.predict import rollout_solver
from mpnode_cli.training.run import checkpoint_path
from mpnode_cli.training.simulate import simulate

S = 3


@pytest.fixture(scope="module")
def ens(tmp_path_factory):
    """A 3-member MP-NODE ensemble trained 8 epochs on gene dynamics on a 2×2 grid (ER),
    and a zero-shot set on a 4×4 Barabási–Albert graph (in-degrees up to 8 against 3)."""
    root = tmp_path_factory.mktemp("ensemble")
    own, big = root / "own.h5", root / "big.h5"
    generate(GenerateConfig(system="gene", grid=2, topology="er", trajectories=48, t_end=2.0,
                            dt=0.1, out=own))
    generate(GenerateConfig(system="gene", grid=4, topology="ba", trajectories=16, t_end=2.0,
                            dt=0.1, out=big))
    train(TrainConfig(dataset=own, run_dir=root / "run", batch_size=16, lr=1e-2, epochs=8,
                      plots=False, seeds=S, dtype="float64"))
    return SimpleNamespace(root=root, own=own, big=big,
                           path=checkpoint_path(root / "run", "best"))


def member_rollouts(ckpt, data: TrajectoryData) -> np.ndarray:
    """`[S, K, T, N, D]` normalized: each member rolled out alone, as a model of its own."""
    norm = ckpt.build_normalizer()
    batch = data.take(torch.arange(len(data)))
    x0 = norm.norm_x(batch.states[:, 0]).double()  # (K, N, D)
    out = []
    for k in range(ckpt.members):
        model = member_checkpoint(ckpt, k).build_model().eval()
        with torch.no_grad():
            states = model.rollout(x0, data.time, batch.graph().double(),
                                   solver=rollout_solver(ckpt)).states
        out.append(states.double().numpy())
    return np.stack(out)


def test_evaluate_scores_the_mean_of_the_members_rolled_out_alone(ens):
    ckpt = load_checkpoint(ens.path)
    data = TrajectoryData.load(ens.own).subset("test")
    norm = ckpt.build_normalizer()
    truth = norm.norm_x(data.states).double().numpy()[:, 1:]  # (K, T-1, N, D)
    preds = member_rollouts(ckpt, data)[:, :, 1:]  # (S, K, T-1, N, D)
    report = evaluate_checkpoint(ckpt, TrajectoryData.load(ens.own), split="test")
    result = report["result"]
    assert result["mse"] == pytest.approx(((preds.mean(0) - truth) ** 2).mean(), rel=1e-5)
    member_mse = ((preds - truth) ** 2).mean(axis=(1, 2, 3, 4))  # (S,)
    assert [m["mse"] for m in result["members"]] == pytest.approx(member_mse, rel=1e-5)
    assert result["members_mean"]["mse"] == pytest.approx(np.mean(member_mse), rel=1e-5)
    assert result["members_std"]["mse"] == pytest.approx(np.std(member_mse), rel=1e-4)
    spread = preds.std(axis=0)  # (K, T-1, N, D), population std as numpy's default
    assert result["spread"] == pytest.approx(spread.mean(), rel=1e-4)
    rmse = np.sqrt(((preds.mean(0) - truth) ** 2).mean(axis=(1, 2, 3)))
    corr = np.corrcoef(spread.mean(axis=(1, 2, 3)), rmse)[0, 1]
    assert result["spread_error_corr"] == pytest.approx(corr, abs=1e-4)
    for k in range(S):  # each member's errors are those of the member evaluated alone
        alone = evaluate_checkpoint(member_checkpoint(ckpt, k), TrajectoryData.load(ens.own),
                                    split="test")["result"]
        assert result["members"][k]["mse"] == pytest.approx(alone["mse"], rel=1e-5)
        assert alone["members"] is None and alone["spread"] is None


def test_evaluate_plot_draws_the_spread_of_the_members(ens, tmp_path):
    from mpnode_cli.training.evaluate import predict

    ckpt = load_checkpoint(ens.path)
    data = TrajectoryData.load(ens.own).subset("test")
    norm = ckpt.build_normalizer()
    pred = predict(ckpt.build_model(), data, norm, torch.arange(2), solver=rollout_solver(ckpt))
    members = member_rollouts(ckpt, data.select(torch.arange(2)))
    physical = members * norm.x_std.double().numpy() + norm.x_mean.double().numpy()
    np.testing.assert_allclose(pred.spread.numpy(), physical.std(axis=0), rtol=1e-4,
                               atol=1e-5)
    np.testing.assert_allclose(pred.pred.numpy(), physical.mean(axis=0), rtol=1e-5, atol=1e-5)
    result = invoke("evaluate", ens.path, ens.own, "--plot", "--plot-dir", tmp_path)
    assert result.exit_code == 0, result.output
    assert (tmp_path / "own-test-rollout.png").stat().st_size > 0


def test_evaluate_table_shows_the_members_mean_and_std(ens):
    result = invoke("evaluate", ens.path, ens.own, "--json")
    assert result.exit_code == 0, result.output
    row = json.loads(result.output)["result"]
    mse = [m["mse"] for m in row["members"]]
    table = invoke("evaluate", ens.path, ens.own)
    assert table.exit_code == 0, table.output
    line = next(x for x in table.output.splitlines() if "members' MSE" in x)
    assert f"{fmt(float(np.mean(mse)))} ± {fmt(float(np.std(mse)))}" in line
    assert "(mean ± std of 3)" in line and "spread-error correlation" in table.output


def test_simulate_writes_the_members_mean_and_their_std(ens, tmp_path):
    ckpt = load_checkpoint(ens.path)
    data = TrajectoryData.load(ens.big)
    x0, adjacency = data.states[:5, 0].numpy(), data.graphs.dense()[0]
    np.save(tmp_path / "x0.npy", x0)
    np.save(tmp_path / "a.npy", adjacency)
    out = tmp_path / "sim.h5"
    summary = simulate(SimulateConfig(checkpoint=ens.path, x0=tmp_path / "x0.npy",
                                      adjacency=tmp_path / "a.npy", t_end=2.0, dt=0.1,
                                      out=out, dtype="float64"))
    assert summary.members == S
    norm = ckpt.build_normalizer()
    mean, std = norm.x_mean.double().numpy(), norm.x_std.double().numpy()
    physical = []
    for k in range(S):
        model = member_checkpoint(ckpt, k).build_model().eval()
        with torch.no_grad():
            states = model.rollout(norm.norm_x(torch.from_numpy(x0)).double(),
                                   torch.arange(21, dtype=torch.float64) * 0.1,
                                   torch.from_numpy(adjacency).double().expand(5, -1, -1),
                                   solver=rollout_solver(ckpt)).states
        physical.append(states.double().numpy() * std + mean)  # (K, T, N, D)
    physical = np.stack(physical)
    with h5py.File(out) as f:
        np.testing.assert_allclose(f["states"][()], physical.mean(axis=0), rtol=1e-5,
                                   atol=1e-5)
        np.testing.assert_allclose(f["hidden/ensemble_std"][()], physical.std(axis=0),
                                   rtol=1e-4, atol=1e-5)
    assert invoke("check", out).exit_code == 0
    assert invoke("info", out).exit_code == 0


def test_the_spread_grows_where_the_error_does(ens):
    ckpt = load_checkpoint(ens.path)
    own = evaluate_checkpoint(ckpt, TrajectoryData.load(ens.own), split="all")["result"]
    big = evaluate_checkpoint(ckpt, TrajectoryData.load(ens.big), split="all",
                              verb="zeroshot")["result"]
    assert big["mse"] > 5 * own["mse"]
    assert big["spread"] > 2 * own["spread"], (own["spread"], big["spread"])


def test_member_k_and_the_exported_member_give_identical_errors(ens, tmp_path):
    k, out = 1, tmp_path / "member1.pt"
    exported = invoke("check", ens.path, "--member", k, "--out", out)
    assert exported.exit_code == 0, exported.output
    single = load_checkpoint(out)
    ensemble = load_checkpoint(ens.path)
    assert single.members == 1 and "members" not in single.model_config
    assert single.train_config["seeds"] == 1
    assert single.train_config["seed"] == ensemble.train_config["seed"] + k
    assert single.optimizer is None and not single.loop and not single.rng
    assert single.normalizer == ensemble.normalizer and single.dataset == ensemble.dataset
    for name, value in single.state_dict.items():
        assert torch.equal(value, ensemble.state_dict[f"members.{k}.{name}"])
    assert invoke("check", out).exit_code == 0
    for verb, args in (("evaluate", (ens.own,)), ("zeroshot", (ens.big,))):
        by_member = json.loads(invoke(verb, ens.path, *args, "--member", k, "--json").output)
        by_file = json.loads(invoke(verb, out, *args, "--json").output)
        key = "datasets" if verb == "zeroshot" else None
        a = by_member[key][0]["result"] if key else by_member["result"]
        b = by_file[key][0]["result"] if key else by_file["result"]
        assert {n: a[n] for n in ("mse", "huber", "rmse", "mse_vs_time", "failed")} == {
            n: b[n] for n in ("mse", "huber", "rmse", "mse_vs_time", "failed")}
        assert by_member["member"] == k


def test_simulate_member_k_equals_the_exported_member(ens, tmp_path):
    out = tmp_path / "member2.pt"
    assert invoke("check", ens.path, "--member", 2, "--out", out).exit_code == 0
    np.save(tmp_path / "x0.npy", TrajectoryData.load(ens.own).states[:3, 0].numpy())
    np.save(tmp_path / "a.npy", TrajectoryData.load(ens.own).graphs.dense()[0])
    common = ("--x0", tmp_path / "x0.npy", "--adjacency", tmp_path / "a.npy", "--t-end", 1,
              "--dt", 0.1)
    a = invoke("simulate", ens.path, *common, "--member", 2, "--out", tmp_path / "a.h5")
    b = invoke("simulate", out, *common, "--out", tmp_path / "b.h5")
    assert a.exit_code == 0 and b.exit_code == 0, a.output + b.output
    with h5py.File(tmp_path / "a.h5") as fa, h5py.File(tmp_path / "b.h5") as fb:
        assert np.array_equal(fa["states"][()], fb["states"][()])
        assert "ensemble_std" not in fa["hidden"] and "ensemble_std" not in fb["hidden"]
        assert json.loads(fa.attrs["prediction"])["member"] == 2


@pytest.mark.parametrize("member", ["3", "-1"])
def test_a_member_out_of_range_is_one_line_and_exit_2(ens, tmp_path, member):
    np.save(tmp_path / "x0.npy", TrajectoryData.load(ens.own).states[:2, 0].numpy())
    np.save(tmp_path / "a.npy", TrajectoryData.load(ens.own).graphs.dense()[0])
    for args in (("evaluate", ens.path, ens.own), ("zeroshot", ens.path, ens.big),
                 ("simulate", ens.path, "--x0", tmp_path / "x0.npy", "--adjacency",
                  tmp_path / "a.npy", "--t-end", 1, "--dt", 0.1, "--out", tmp_path / "s.h5"),
                 ("check", ens.path, "--out", tmp_path / "m.pt")):
        result = invoke(*args, "--member", member)
        assert result.exit_code == 2, result.output
        assert result.output.strip().splitlines() == [
            f"Error: --member: {ens.path} holds members 0 to 2, not {member}"]
    assert not (tmp_path / "s.h5").exists() and not (tmp_path / "m.pt").exists()


def test_member_of_a_single_model_is_refused(ens, tmp_path):
    single = tmp_path / "single.pt"
    assert invoke("check", ens.path, "--member", 0, "--out", single).exit_code == 0
    for args in (("evaluate", single, ens.own), ("zeroshot", single, ens.big),
                 ("check", single, "--out", tmp_path / "again.pt")):
        result = invoke(*args, "--member", 0)
        assert result.exit_code == 2, result.output
        (line,) = result.output.strip().splitlines()
        assert line.startswith(f"Error: --member: {single} holds one model, not an ensemble")
    lone = invoke("check", ens.path, "--member", 0)
    assert lone.exit_code == 2 and lone.output.startswith("Error: --member and --out")


def test_spread_error_correlation_is_pearsons():
    rng = np.random.default_rng(0)
    spread, error = rng.random(50), rng.random(50)
    error = error + 2 * spread  # correlated
    got = spread_error_correlation(torch.from_numpy(spread).float(),
                                   torch.from_numpy(error).float())
    assert got == pytest.approx(np.corrcoef(spread, error)[0, 1], abs=1e-6)
    assert np.isnan(spread_error_correlation(torch.ones(5), torch.arange(5.0)))
    assert np.isnan(spread_error_correlation(torch.arange(2.0), torch.arange(2.0)))
