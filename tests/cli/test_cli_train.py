"""`mpnode train / evaluate / zeroshot / finetune / compare` end to end, through `CliRunner`.

One small story on coupled Lorenz: train on N=3, evaluate, zero-shot on N=7, finetune onto
N=5, compare the runs — and the one-line refusals along the way.
"""

from __future__ import annotations

import json

import pytest
import typer
from conftest import invoke
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.models.registry import OPTIONS
from mpnode_cli.training import loop
from mpnode_cli.training.checkpoint import load_checkpoint

runner = CliRunner()
FAST = ["--batch-size", "8", "--lr", "1e-2", "--no-plots"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Lorenz with 3, 5 and 7 nodes and a gene set (node_dim 1), 0.5 s at dt 0.05."""
    root = tmp_path_factory.mktemp("data")
    sizes = {"l3": (3, 40), "l5": (5, 20), "l7": (7, 10)}
    paths = {}
    for name, (nodes, k) in sizes.items():
        paths[name] = generate(GenerateConfig(system="lorenz", nodes=nodes, trajectories=k,
                                              t_end=0.5, dt=0.05, out=root / f"{name}.h5")).path
    paths["gene"] = generate(GenerateConfig(system="gene", grid=2, trajectories=10, t_end=0.5,
                                            dt=0.1, out=root / "gene.h5")).path
    return paths


@pytest.fixture(scope="module")
def trained(data, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "l3"
    result = runner.invoke(app, ["train", str(data["l3"]), "--epochs", "3", "--run-dir",
                                 str(run), *FAST])
    assert result.exit_code == 0, result.output
    assert "best epoch" in result.output and "threads: " in result.stderr
    return run


def one_line_error(result, code=2) -> str:
    assert result.exit_code == code, result.output
    lines = [line for line in result.output.splitlines() if line.startswith("Error:")]
    assert len(lines) == 1, result.output
    return lines[0]


def test_train_writes_a_run_folder(trained):
    assert {p.name for p in trained.iterdir()} >= {"config.json", "metrics.jsonl",
                                                   "summary.json", "checkpoints"}
    summary = json.loads((trained / "summary.json").read_text())
    assert summary["epochs"] == 3 and summary["num_nodes"] == 3 and summary["test"]
    assert summary["threads"] >= 1  # the CPU threads torch used, recorded by the CLI


def test_evaluate_table_json_and_plots(trained, data, tmp_path):
    best = trained / "checkpoints" / "best.pt"
    result = invoke("evaluate", best, data["l3"])
    assert result.exit_code == 0, result.output
    assert "MSE (normalized)" in result.output and "RMSE z" in result.output
    assert "hold-x(0) MSE" in result.output and "time-mean MSE" in result.output
    assert "the time mean of the train split of l3.h5" in result.output
    result = invoke("evaluate", best, data["l3"], "--split", "validation", "--json", "--plot",
                    "--plot-dir", tmp_path)
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    summary = json.loads((trained / "summary.json").read_text())
    assert report["result"]["mse"] == pytest.approx(summary["min_val_mse"], rel=1e-6)
    assert sorted(p.name for p in tmp_path.glob("*.png")) == [
        "l3-validation-error.png", "l3-validation-rollout.png"]


def test_zeroshot_onto_seven_nodes(trained, data):
    best = trained / "checkpoints" / "best.pt"
    result = invoke("zeroshot", best, data["l5"], data["l7"], "--json")
    assert result.exit_code == 0, result.output
    rows = json.loads(result.output)["datasets"]
    assert [r["num_nodes"] for r in rows] == [5, 7]
    assert all(r["result"]["failed"] == 0 and r["result"]["mse"] > 0 for r in rows)
    assert all(r["baselines"]["hold_x0"] > 0 and r["baselines"]["time_mean"] > 0 for r in rows)
    table = invoke("zeroshot", best, data["l7"])
    assert table.exit_code == 0 and "l7.h5" in table.output


def test_mismatched_node_dim_is_refused_in_one_line(trained, data):
    best = trained / "checkpoints" / "best.pt"
    line = one_line_error(invoke("zeroshot", best, data["l7"], data["gene"]))
    assert "node_dim 1 but the checkpoint expects 3" in line
    line = one_line_error(invoke("finetune", best, data["gene"], "--epochs", "1"))
    assert "finetune needs the same per-node state size" in line
    line = one_line_error(invoke("evaluate", best, data["gene"]))
    assert "node_dim" in line


def test_finetune_onto_five_nodes_then_compare(trained, data, tmp_path):
    best = trained / "checkpoints" / "best.pt"
    run = tmp_path / "ft"
    result = invoke("finetune", best, data["l5"], "--epochs", "2", "--trajectories", "5",
                    "--run-dir", run, *FAST)
    assert result.exit_code == 0, result.output
    assert "finetuned from" in result.output
    child = load_checkpoint(run / "checkpoints" / "last.pt")
    assert child.dataset["num_nodes"] == 5 and child.parent_sha256
    config = json.loads((run / "config.json").read_text())
    assert config["init_checkpoint"] == str(best) and config["trajectories"] == 5

    result = invoke("compare", trained, run)
    assert result.exit_code == 0, result.output
    assert "l3" in result.output and "ft" in result.output and "Table-2" in result.output
    summaries = json.loads(invoke("compare", trained, run, "--json").output)
    assert [s["num_nodes"] for s in summaries] == [3, 5]
    assert summaries[1]["table2"] == pytest.approx(
        summaries[1]["best_epoch"] * summaries[1]["min_val_loss"])


def test_resume_and_its_refusals(data, tmp_path):
    run = tmp_path / "run"
    assert invoke("train", data["l3"], "--epochs", "1", "--run-dir", run, *FAST).exit_code == 0
    assert "--resume" in one_line_error(invoke("train", data["l3"], "--run-dir", run))
    assert "only --epochs" in one_line_error(invoke("train", "--resume", run, "--lr", "0.1"))
    result = invoke("train", "--resume", run, "--epochs", "2")
    assert result.exit_code == 0, result.output
    assert json.loads((run / "summary.json").read_text())["epochs"] == 2
    assert "DATASET" in one_line_error(invoke("train"))
    assert "no such dataset" in one_line_error(invoke("train", tmp_path / "missing.h5"))
    assert "graph" in one_line_error(invoke("train", data["l3"], "--graph", "ring"))
    assert "not an mpnode checkpoint" in one_line_error(
        invoke("evaluate", run / "config.json", data["l3"]))


def test_train_on_two_datasets_then_finetune_and_resume(trained, data, tmp_path):
    run = tmp_path / "two"
    result = invoke("train", data["l3"], data["l5"], "--epochs", "2", "--run-dir", run, *FAST)
    assert result.exit_code == 0, result.output
    assert "l3 (N=3), l5 (N=5)" in result.output  # the summary table names both
    summary = json.loads((run / "summary.json").read_text())
    assert summary["epochs"] == 2 and list(summary["by_dataset"]) == ["l3", "l5"]
    assert all(d["test"]["mse"] > 0 for d in summary["by_dataset"].values())
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [list(r["val_mse_by_dataset"]) for r in rows] == [["l3", "l5"]] * 3
    result = invoke("train", "--resume", run, "--epochs", "3")
    assert result.exit_code == 0, result.output
    line = one_line_error(invoke("train", data["l3"], "--resume", run, "--epochs", "4"))
    assert "trained on 2 datasets but 1 was given" in line
    ft = tmp_path / "ft"
    result = invoke("finetune", trained, data["l5"], data["l7"], "--epochs", "1",
                    "--run-dir", ft, *FAST)
    assert result.exit_code == 0, result.output
    child = load_checkpoint(ft / "checkpoints" / "last.pt")
    assert [r["num_nodes"] for r in child.dataset["datasets"]] == [5, 7]


def test_datasets_that_do_not_go_together_are_refused(data, tmp_path):
    line = one_line_error(invoke("train", data["l3"], data["gene"], "--run-dir", tmp_path / "r"))
    assert "has system gene but l3.h5 has lorenz" in line
    line = one_line_error(invoke("train", data["l3"], data["l5"], "--stream"))
    assert "--stream reads one dataset" in line
    line = one_line_error(invoke("train", data["l3"], data["l3"]))
    assert "holds the same data as l3.h5" in line
    assert not (tmp_path / "r").exists()


def test_ctrl_c_exits_130_after_saving_last(data, tmp_path, monkeypatch):
    epoch = loop.train_epoch

    def interrupted(*args):
        if args[3] == 2:  # the epoch number
            raise KeyboardInterrupt
        return epoch(*args)

    monkeypatch.setattr(loop, "train_epoch", interrupted)
    run = tmp_path / "run"
    result = invoke("train", data["l3"], "--epochs", "5", "--run-dir", run, *FAST)
    assert result.exit_code == 130, result.output
    assert f"mpnode train --resume {run}" in result.output
    assert load_checkpoint(run / "checkpoints" / "last.pt").epoch == 1


def test_model_options_of_the_cli_are_the_ones_the_models_declare():
    command = typer.main.get_command(app).commands["train"]
    panel = {p.name for p in command.params
             if getattr(p, "rich_help_panel", None) == "Model options"}
    declared = {name for options in OPTIONS.values() for name in options.model_fields}
    assert panel == declared | {"model"}
    finetune = typer.main.get_command(app).commands["finetune"]
    assert not declared & {p.name for p in finetune.params}  # the checkpoint decides
    help_text = invoke("train", "--help").output
    assert "--message-dim" in help_text and "--no-messages" in help_text
    assert "--step-noise" in help_text and "l2s (128)" in help_text


def test_train_options_are_the_config_fields_with_their_descriptions():
    """No default or help is written twice: each option of a `TrainConfig` field leaves
    its value out (None) and opens its help with the field's description."""
    from mpnode_cli.config.train import TrainConfig

    for verb in ("train", "finetune"):
        command = typer.main.get_command(app).commands[verb]
        for param in command.params:
            field = TrainConfig.model_fields.get(param.name)
            if field is None or param.name in ("dataset", "datasets"):
                continue
            assert param.default is None, (verb, param.name)
            assert param.help.startswith(field.description.removesuffix(".")), param.name
        panels = {getattr(p, "rich_help_panel", None) for p in command.params}
        assert {"Data", "Recipe and optimization", "Solver", "Output and run"} <= panels


def test_model_options_from_the_command_line_and_a_config_file(data, tmp_path):
    line = one_line_error(invoke("train", data["l3"], "--model", "gnode", "--message-dim", 2))
    assert "model 'gnode' has no option 'message_dim'" in line
    (tmp_path / "c.toml").write_text('model = "gnode"\n[model_options]\nhidden = 8\n'
                                     'depth = 2\n')
    run = tmp_path / "run"
    result = invoke("train", data["l3"], "--config", tmp_path / "c.toml", "--depth", 3,
                    "--epochs", 1, "--run-dir", run, *FAST)
    assert result.exit_code == 0, result.output
    config = json.loads((run / "config.json").read_text())
    assert config["model"] == "gnode"
    # Lorenz recommends the mean, and a recommendation applies to any model declaring it.
    assert config["model_options"] == {"hidden": 8, "depth": 3, "graph": "sys",
                                       "aggregate": "mean"}
    (tmp_path / "bad.toml").write_text("[model_options]\nlatent = 8\n")
    line = one_line_error(invoke("train", data["l3"], "--config", tmp_path / "bad.toml"))
    assert "model 'mpnode' has no option 'latent'" in line
    assert "only --epochs" in one_line_error(invoke("train", "--resume", run, "--hidden", 4))
