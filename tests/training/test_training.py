"""Training: it learns, resumes exactly, survives bad steps; checkpoints and evaluation."""

from __future__ import annotations

import json
import math

import pytest
import torch
from conftest import gene_data

from mpnode_cli.config.train import TrainConfig
from mpnode_cli.config.upgrade import upgrade_train_fields
from mpnode_cli.data.dataset import Normalizer, TrajectoryData
from mpnode_cli.models.mpnode import MPNODE
from mpnode_cli.models.options import L2SOptions
from mpnode_cli.solver import Status
from mpnode_cli.training import loop, step_memory
from mpnode_cli.training.checkpoint import (
    FORMAT,
    FORMAT_VERSION,
    CheckpointFormatError,
    file_sha256,
    load_checkpoint,
    save_checkpoint,
)
from mpnode_cli.training.compat import check_compatible
from mpnode_cli.training.evaluate import evaluate, predict
from mpnode_cli.training.loop import TrainingDiverged, TrainingInterrupted, train
from mpnode_cli.training.run import checkpoint_path, read_config, read_metrics


@pytest.fixture(scope="module")
def gene(gene_2x2):
    """Gene dynamics on a 2×2 grid (ER graph): 48 trajectories × 21 samples."""
    return gene_2x2


def config(dataset, run_dir, **kw) -> TrainConfig:
    fields = {"dataset": dataset, "run_dir": run_dir, "batch_size": 16, "lr": 1e-2,
              "epochs": 4, "plots": False}
    return TrainConfig(**(fields | kw))


@pytest.fixture(scope="module")
def four(gene, tmp_path_factory):
    """`config(gene, ...)` trained whole, 4 epochs in one go: the run folder, which the
    tests only read (the reference of the resumed runs, and a checkpoint to load)."""
    run_dir = tmp_path_factory.mktemp("four") / "run"
    train(config(gene, run_dir))
    return run_dir


def rows(run_dir):
    """Metrics rows without their timings (which differ between identical runs)."""
    return [{k: v for k, v in r.items() if not k.endswith("seconds")}
            for r in read_metrics(run_dir)]


def test_learning_cuts_validation_loss_tenfold(gene, tmp_path):
    summary = train(config(gene, tmp_path / "run", epochs=20, plots=True))
    metrics = read_metrics(tmp_path / "run")
    assert [r["epoch"] for r in metrics] == list(range(21))  # epoch 0: the starting weights
    after_one_epoch = metrics[1]["val_loss"]
    assert summary.min_val_loss <= after_one_epoch / 10, (after_one_epoch, summary.min_val_loss)
    assert summary.best_epoch == min(metrics, key=lambda r: r["val_loss"])["epoch"]
    assert summary.table2 == pytest.approx(summary.best_epoch * summary.min_val_loss)
    assert summary.test["mse"] < metrics[0]["val_mse"] / 10
    # The recipe's affine update, D = 1, M = 3: F and G from x, 1 → 32 → 32 → (D + M) + D·M
    # + M·M = 16; ψ from [x, m], 4 → 32 → 3; the first messages from x, 1 → 32 → 3.
    # (The authors' MLP of [x, mean m] gives 4 → 32 → 32 → 4 = 1348: MPNODE.jl
    # exps/models.jl:92-95.)
    net = 1 * 32 + 32 + 32 * 32 + 32 + 32 * 16 + 16
    assert summary.parameters == net + (4 * 32 + 32 + 32 * 3 + 3) + (1 * 32 + 32 + 32 * 3 + 3)
    files = {p.relative_to(tmp_path / "run").as_posix() for p in (tmp_path / "run").rglob("*")}
    assert {"config.json", "metrics.jsonl", "summary.json", "checkpoints/best.pt",
            "checkpoints/last.pt", "plots/gene-test-rollout.png",
            "plots/gene-test-error.png"} <= files
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["best_epoch"] == (
        summary.best_epoch)
    assert TrainConfig(**json.loads((tmp_path / "run" / "config.json").read_text())).epochs == 20


def test_two_plus_two_epochs_equal_four(gene, four, tmp_path):
    train(config(gene, tmp_path / "resumed", epochs=2))
    train(config(gene, tmp_path / "resumed"), resume=True)
    a = load_checkpoint(checkpoint_path(four, "last"))
    b = load_checkpoint(checkpoint_path(tmp_path / "resumed", "last"))
    for name, value in a.state_dict.items():
        assert torch.equal(value, b.state_dict[name]), name
    for key, state in a.optimizer["state"].items():
        for name, value in state.items():
            assert torch.equal(value, b.optimizer["state"][key][name]), (key, name)
    assert rows(four) == rows(tmp_path / "resumed")


def test_ctrl_c_saves_last_completed_epoch_and_resume_continues_it(gene, four, tmp_path):
    def interrupt(event):
        if event["event"] == "batch" and event["epoch"] == 3:
            raise KeyboardInterrupt

    with pytest.raises(TrainingInterrupted) as info:
        train(config(gene, tmp_path / "cut"), progress=interrupt)
    assert info.value.epoch == 2
    assert load_checkpoint(checkpoint_path(tmp_path / "cut", "last")).epoch == 2
    train(config(gene, tmp_path / "cut"), resume=True)
    assert rows(tmp_path / "cut") == rows(four)


def test_checkpoint_round_trip(gene, four, tmp_path):
    path = checkpoint_path(four, "best")
    raw = torch.load(path, weights_only=True)  # only tensors and plain data inside
    assert raw["format"] == FORMAT and raw["format_version"] == FORMAT_VERSION
    assert set(raw) >= {"model_kind", "model_config", "state_dict", "normalizer",
                        "train_config", "dataset", "epoch", "optimizer", "rng", "loop"}
    ckpt = load_checkpoint(path)
    again = save_checkpoint(tmp_path / "copy.pt", ckpt)
    assert [p.name for p in tmp_path.iterdir() if p.suffix == ".tmp"] == []
    copy = load_checkpoint(again)
    data = TrajectoryData.load(gene).subset("validation")
    outs = [predict(c.build_model(), data, c.build_normalizer(), torch.arange(3)).pred
            for c in (ckpt, copy)]
    torch.testing.assert_close(outs[0], outs[1], rtol=0, atol=0)
    assert copy.dataset["fingerprint"] == TrajectoryData.load(gene).fingerprint
    assert len(file_sha256(path)) == 64

    torch.save({"format": FORMAT, "format_version": 99}, tmp_path / "newer.pt")
    with pytest.raises(CheckpointFormatError, match="newer"):
        load_checkpoint(tmp_path / "newer.pt")
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    with pytest.raises(CheckpointFormatError, match="not an mpnode checkpoint"):
        load_checkpoint(tmp_path / "junk.pt")


def flaky_loss(fail_calls):
    """The MSE loss, but NaN on the given (1-based) calls from training."""
    calls = {"n": 0}
    mse = loop.LOSSES["mse"]

    def loss(pred, target):
        calls["n"] += 1
        value = mse(pred, target)
        return value * math.nan if calls["n"] in fail_calls else value

    return loss


def test_bad_step_is_skipped_and_runs_of_them_roll_back(gene, tmp_path, monkeypatch):
    # 34 train trajectories in batches of 16: 3 steps per epoch.
    monkeypatch.setitem(loop.LOSSES, "mse", flaky_loss({2, 4, 5}))
    summary = train(config(gene, tmp_path / "run", epochs=2, max_bad_steps=2))
    metrics = read_metrics(tmp_path / "run")
    assert [r["skipped"] for r in metrics[1:]] == [1, 2]
    assert summary.skipped_batches == 3 and summary.restores == 1
    assert metrics[1]["lr"] == 1e-2 and metrics[2]["lr"] == 5e-3  # halved by the rollback
    weights = load_checkpoint(checkpoint_path(tmp_path / "run", "last")).state_dict
    assert all(torch.isfinite(w).all() for w in weights.values())


def test_solver_failure_in_a_batch_skips_it(gene, tmp_path, monkeypatch):
    rollout = MPNODE.rollout
    calls = {"n": 0}

    def failing(self, *args, **kwargs):
        out = rollout(self, *args, **kwargs)
        if torch.is_grad_enabled():  # a training step, not validation
            calls["n"] += 1
            if calls["n"] == 1:
                out.status[0] = Status.MAX_STEPS
        return out

    monkeypatch.setattr(MPNODE, "rollout", failing)
    # The memory check before the first step rolls out with gradients too; not here.
    monkeypatch.setattr(step_memory, "check_run", lambda model, config, *args: config)
    summary = train(config(gene, tmp_path / "run", epochs=1))
    assert summary.skipped_batches == 1 and summary.restores == 0


def test_persistent_bad_steps_stop_with_a_reason(gene, tmp_path, monkeypatch):
    monkeypatch.setitem(loop.LOSSES, "mse", flaky_loss(set(range(1, 100))))
    with pytest.raises(TrainingDiverged, match="non-finite loss"):
        train(config(gene, tmp_path / "run", epochs=3, max_bad_steps=1, min_lr=4e-3))


def test_horizon_curriculum_grows_to_the_whole_trajectory(gene, tmp_path):
    cfg = config(gene, tmp_path / "run", epochs=4, horizon_curriculum=True,
                 curriculum_start=5, curriculum_epochs=2)
    assert [loop.epoch_horizon(cfg, e, 21) for e in (1, 2, 3, 4)] == [5, 13, 21, 21]
    train(cfg)
    assert [r["horizon"] for r in read_metrics(tmp_path / "run")[1:]] == [5, 13, 21, 21]


def test_finetune_starts_from_the_checkpoint_with_its_normalization(gene, tmp_path):
    train(config(gene, tmp_path / "base", epochs=3))
    parent = checkpoint_path(tmp_path / "base", "best")
    summary = train(config(gene, tmp_path / "ft", epochs=1, init_checkpoint=parent,
                           trajectories=10, model_options={"hidden": 7}))
    ckpt, child = load_checkpoint(parent), load_checkpoint(checkpoint_path(tmp_path / "ft", "last"))
    assert child.parent_sha256 == file_sha256(parent) == summary.parent_sha256
    assert child.model_config == ckpt.model_config  # architecture from the checkpoint
    assert child.normalizer == ckpt.normalizer
    assert child.optimizer["state"][0]["step"] == 1  # fresh Adam: one step of 10 trajectories
    # Epoch 0 of the finetune is the parent's own validation loss.
    assert read_metrics(tmp_path / "ft")[0]["val_loss"] == pytest.approx(
        ckpt.metrics["val_loss"], rel=1e-6)
    renorm = train(config(gene, tmp_path / "renorm", epochs=1, init_checkpoint=parent,
                          renormalize=True, trajectories=5))
    assert renorm.parent_sha256 == summary.parent_sha256
    assert load_checkpoint(checkpoint_path(tmp_path / "renorm", "last")).normalizer != (
        ckpt.normalizer)


def test_evaluate_matches_a_direct_computation(gene, four):
    ckpt = load_checkpoint(checkpoint_path(four, "best"))
    model, norm = ckpt.build_model(), ckpt.build_normalizer()
    data = TrajectoryData.load(gene).subset("all")
    result = evaluate(model, data, norm, batch_size=5)  # batches of unequal size
    pred = predict(model, data, norm, torch.arange(len(data)))
    err = (norm.norm_x(pred.pred) - norm.norm_x(pred.true))[:, 1:].double()
    assert result.mse == pytest.approx(float(err.pow(2).mean()), rel=1e-5)
    phys = (pred.pred - pred.true)[:, 1:].double()
    assert result.rmse == pytest.approx(phys.pow(2).mean(dim=(0, 1, 2)).sqrt().tolist(), rel=1e-5)
    curve = torch.tensor(result.mse_vs_time)
    assert curve[0] == 0 and float(curve[1:].mean()) == pytest.approx(result.mse, rel=1e-6)
    huber = torch.nn.functional.huber_loss(err, torch.zeros_like(err), reduction="none")
    assert result.huber == pytest.approx(float(huber.sum(dim=(1, 3)).mean()), rel=1e-5)
    # node-mse: each node's squared error over its own variance along the whole trajectory.
    true = norm.norm_x(pred.true).double()
    variance = (true - true.mean(dim=1, keepdim=True)).pow(2).mean(dim=1, keepdim=True)
    node_mse = err.pow(2) / (variance + 1e-3)
    assert result.node_mse == pytest.approx(float(node_mse.mean()), rel=1e-5)


def test_a_model_that_is_not_transferable_refuses_another_size(gene):
    data = TrajectoryData.load(gene)  # N = 4, node_dim 1
    node = {"node_dim": 1, "num_nodes": 4}
    check_compatible("node", node, 4, data, "zeroshot")  # the monolithic NODE, same N: fine
    with pytest.raises(ValueError, match="trained on 3 and only runs on graphs of that size"):
        check_compatible("node", node | {"num_nodes": 3}, 3, data, "zeroshot")
    with pytest.raises(ValueError, match="node_dim 1 but the checkpoint expects 3"):
        check_compatible("mpnode", {"node_dim": 3}, 4, data, "zeroshot")


def test_model_options_come_from_the_model_unless_given(gene, tmp_path):
    train(config(gene, tmp_path / "mp", epochs=1))
    resolved = json.loads((tmp_path / "mp" / "config.json").read_text())["model_options"]
    assert (resolved["hidden"], resolved["layers"], resolved["message_dim"]) == (32, 2, 3)
    train(config(gene, tmp_path / "gnode", epochs=1, model="gnode",
                 model_options={"hidden": 8, "graph": "full"}))
    ckpt = load_checkpoint(checkpoint_path(tmp_path / "gnode", "last"))
    assert ckpt.model_kind == "gnode" and ckpt.model_config["hidden"] == 8
    with pytest.raises(ValueError, match="model 'gnode' has no option 'message_dim'"):
        train(config(gene, tmp_path / "bad", epochs=1, model="gnode",
                     model_options={"message_dim": 2}))
    with pytest.raises(ValueError, match=r"model 'mpnode' option hidden: .*greater than or"):
        train(config(gene, tmp_path / "bad", epochs=1, model_options={"hidden": 0}))
    assert not (tmp_path / "bad").exists()  # refused before anything was written


def test_model_options_round_trip_through_config_json_and_checkpoint(gene, tmp_path):
    given = {"latent": 8, "hidden": 8, "steps": 2, "history": 2, "step_noise": 0.01}
    train(config(gene, tmp_path / "l2s", epochs=1, model="l2s", model_options=given))
    written = json.loads((tmp_path / "l2s" / "config.json").read_text())
    expected = L2SOptions(**given).model_dump()  # every option, defaults filled in
    assert written["model"] == "l2s" and written["model_options"] == expected
    assert TrainConfig(**written).model_options == expected
    ckpt = load_checkpoint(checkpoint_path(tmp_path / "l2s", "last"))
    assert ckpt.model_config == {"node_dim": 1, "control_dim": 0} | expected
    assert ckpt.train_config["model_options"] == expected
    assert ckpt.build_model().config == ckpt.model_config


def downgrade_to_flat(run_dir, fields):
    """Rewrite a run as the version before `model_options` left it: flat model fields in
    config.json and checkpoints' train_config, checkpoint format 2 (no L2S step_noise)."""
    path = run_dir / "config.json"
    config = json.loads(path.read_text())
    options = config.pop("model_options")
    config |= fields
    path.write_text(json.dumps(config))
    for which in ("best", "last"):
        raw = torch.load(checkpoint_path(run_dir, which), weights_only=True)
        raw["format_version"] = 2
        raw.pop("payload_sha256")  # version 2 carried no digest
        raw["model_config"] = {k: v for k, v in raw["model_config"].items()
                               if k != "step_noise"}
        raw["train_config"] = {k: v for k, v in raw["train_config"].items()
                               if k != "model_options"} | fields
        torch.save(raw, checkpoint_path(run_dir, which))
    return options


def test_a_run_written_with_flat_model_fields_resumes(gene, tmp_path):
    run = tmp_path / "old"
    given = {"latent": 8, "hidden": 8, "steps": 2, "step_noise": 0.02}
    train(config(gene, run, epochs=1, model="l2s", model_options=given))
    options = downgrade_to_flat(run, {
        "latent": 8, "hidden": 8, "steps": 2, "history": 1, "graph": "sys", "layers": 2,
        "message_dim": None, "aggregation": None, "depth": None, "step_noise": 0.02})
    assert load_checkpoint(checkpoint_path(run, "last")).model_config["step_noise"] == 0.02
    train(read_config(run).model_copy(update={"epochs": 2}), resume=True)
    assert json.loads((run / "config.json").read_text())["model_options"] == options
    assert [r["epoch"] for r in read_metrics(run)] == [0, 1, 2]


def test_flat_fields_of_mpnode_map_onto_its_options():
    old = {"dataset": "d.h5", "model": "mpnode", "hidden": 16, "message_dim": 2,
           "aggregation": "dense", "latent": None, "step_noise": 0.003}
    fields = upgrade_train_fields(old)
    assert fields["model_options"] == {"hidden": 16, "message_dim": 2, "backend": "dense"}
    assert TrainConfig(**fields).model == "mpnode"
    assert upgrade_train_fields(fields) == fields


# Several datasets at once (`mpnode_cli.data.pooled`).

@pytest.fixture(scope="module")
def gene9(tmp_path_factory):
    """Gene dynamics on a 3×3 grid: N = 9 beside `gene`'s 4, and 11 samples, not 21."""
    return gene_data(tmp_path_factory.mktemp("data9"), grid=3, trajectories=20, t_end=1.0,
                     name="gene9")


def test_one_dataset_as_a_list_trains_as_one_dataset(gene, tmp_path):
    """The several-datasets path given one file is the one-dataset run, bit for bit, with
    the files and keys of a one-dataset run."""
    train(config(gene, tmp_path / "one", epochs=2))
    train(config([gene], tmp_path / "listed", epochs=2))
    assert rows(tmp_path / "one") == rows(tmp_path / "listed")
    a = load_checkpoint(checkpoint_path(tmp_path / "one", "last"))
    b = load_checkpoint(checkpoint_path(tmp_path / "listed", "last"))
    assert all(torch.equal(v, b.state_dict[k]) for k, v in a.state_dict.items())
    assert a.dataset == b.dataset and "datasets" not in b.dataset
    written = json.loads((tmp_path / "listed" / "config.json").read_text())
    assert written["dataset"] == str(gene.resolve())  # a path, as one-dataset runs write it
    assert not any(k.endswith("_by_dataset") for r in rows(tmp_path / "listed") for k in r)
    summary = json.loads((tmp_path / "listed" / "summary.json").read_text())
    assert summary["by_dataset"] is None


def element_weights(paths, split):
    """K · (T − 1) · N · D of each dataset's split: the weights of pooled MSEs."""
    parts = [TrajectoryData.load(p).subset(split) for p in paths]
    return [len(d) * (d.time.numel() - 1) * d.num_nodes * d.node_dim for d in parts]


def test_two_datasets_of_other_sizes_train_together(gene, gene9, tmp_path):
    events = []
    summary = train(config([gene, gene9], tmp_path / "two", epochs=2), progress=events.append)
    names, run = ["gene", "gene9"], tmp_path / "two"
    # Each epoch takes the batches of both (each of one dataset), ⌈K_i / 16⌉ per dataset.
    trains = [len(TrajectoryData.load(p).subset("train")) for p in (gene, gene9)]
    per_epoch = sum(math.ceil(k / 16) for k in trains)
    assert events[0]["batches"] == per_epoch
    assert sum(e["event"] == "batch" and e["epoch"] == 1 for e in events) == per_epoch
    # Validation: per dataset, and pooled as the element-weighted mean of the two.
    val_weights = element_weights((gene, gene9), "validation")
    metrics = read_metrics(run)
    for row in metrics:
        each = row["val_mse_by_dataset"]
        assert list(each) == names and list(row["val_loss_by_dataset"]) == names
        weighted = sum(each[n] * w for n, w in zip(names, val_weights, strict=True))
        assert row["val_mse"] == pytest.approx(weighted / sum(val_weights), rel=1e-12)
        assert row["val_loss"] == row["val_mse"]  # the loss is the MSE here
    assert summary.best_epoch == min(metrics, key=lambda r: r["val_loss"])["epoch"]
    # Test: per dataset and pooled, with baselines of both kinds.
    test_weights = element_weights((gene, gene9), "test")
    by = summary.by_dataset
    assert list(by) == names and all(by[n]["test"] and by[n]["baselines"] for n in names)
    for what, pick in (("test", "mse"), ("baselines", "hold_x0"), ("baselines", "time_mean")):
        weighted = sum(by[n][what][pick] * w for n, w in zip(names, test_weights, strict=True))
        pooled_value = (summary.test if what == "test" else summary.baselines)[pick]
        assert pooled_value == pytest.approx(weighted / sum(test_weights), rel=1e-12)
    assert [by[n]["num_nodes"] for n in names] == [4, 9]
    # The records: both datasets in config.json and in the checkpoint, normalization pooled.
    written = json.loads((run / "config.json").read_text())
    assert written["dataset"] == [str(gene.resolve()), str(gene9.resolve())]
    ckpt = load_checkpoint(checkpoint_path(run, "best"))
    loaded = [TrajectoryData.load(p) for p in (gene, gene9)]
    assert [r["fingerprint"] for r in ckpt.dataset["datasets"]] == [d.fingerprint for d in loaded]
    assert ckpt.dataset["fingerprint"] == loaded[0].fingerprint  # the first, at the top
    pooled_norm = Normalizer.fit([d.subset("train").states for d in loaded])
    assert ckpt.normalizer == pooled_norm.to_dict()


def test_two_datasets_resume_exactly(gene, gene9, tmp_path):
    train(config([gene, gene9], tmp_path / "whole", epochs=2))
    train(config([gene, gene9], tmp_path / "resumed", epochs=1))
    train(config([gene, gene9], tmp_path / "resumed", epochs=2), resume=True)
    assert rows(tmp_path / "whole") == rows(tmp_path / "resumed")
    with pytest.raises(ValueError, match="are not the 2 datasets this run trained on"):
        train(config([gene9, gene], tmp_path / "resumed", epochs=3), resume=True)


def test_balanced_datasets_weigh_each_by_1_over_its_variance(gene, gene9, tmp_path):
    """`--balance-datasets`: the validation loss that picks the best epoch pools the
    datasets' MSEs with each one's weight times 1 / the variance of its normalized train
    states, computed here with numpy from the files and the checkpoint's normalizer."""
    import numpy as np

    from mpnode_cli.data.hdf5 import read_dataset

    train(config([gene, gene9], tmp_path / "run", epochs=1, balance_datasets=True))
    norm = load_checkpoint(checkpoint_path(tmp_path / "run", "last")).normalizer
    mean, std = np.array(norm["x_mean"]), np.array(norm["x_std"])
    row = read_metrics(tmp_path / "run")[1]
    num = den = 0.0
    for path in (gene, gene9):
        ds = read_dataset(path)
        z = (ds.states[ds.split == 0].astype(np.float64) - mean) / std
        k, t, n, d = ds.states[ds.split == 1].shape
        weight = k * (t - 1) * n * d / z.var()
        num, den = num + weight * row["val_mse_by_dataset"][path.stem], den + weight
    assert row["val_mse"] == pytest.approx(num / den, rel=1e-9)
    plain = train(config([gene, gene9], tmp_path / "plain", epochs=1))
    assert plain.min_val_loss != pytest.approx(row["val_mse"], rel=1e-3)  # it did weigh


def test_a_model_of_one_size_refuses_datasets_of_several(gene, gene9, tmp_path):
    with pytest.raises(ValueError, match="N = 4, 9: train it on datasets of one N"):
        train(config([gene, gene9], tmp_path / "node", epochs=1, model="node"))
    assert not (tmp_path / "node").exists()


def test_a_time_limit_ends_the_run_after_the_epoch_that_reaches_it(gene, tmp_path):
    summary = train(config(gene, tmp_path / "run", epochs=50, time_limit=1e-6))
    assert summary.epochs == 1 and summary.stopped_early == 1
    rows = read_metrics(tmp_path / "run")
    assert [r["epoch"] for r in rows] == [0, 1]
    # Resumed with a budget it has not spent, it goes on.
    spent = sum(r["seconds"] for r in rows)
    resumed = train(config(gene, tmp_path / "run", epochs=3, time_limit=spent * 1e3),
                    resume=True)
    assert resumed.epochs == 3 and resumed.stopped_early is None
