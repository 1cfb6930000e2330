"""Numbers a run cannot use and options that contradict each other are one `Error:` line
(exit 2) before anything is written; what is legal but pointless gets a warning.

Once: `train --lr 1e39` trained until Adam's first float32 step gave a traceback, leaving a
run folder whose resume failed the same way; `--min-lr` above `--lr`, `--wrap-angles` on
data without angles and `generate -p sigma=1 -p sigma=2` ran without a word; `--rtol 1e-20`
ran for minutes a trajectory; `finetune --seeds 3` from one model trained three copies of
it; a CSV naming a state column twice was imported; a dataset whose states never vary
trained to errors of 0 without a word.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.config.train import TrainConfig

FAST = ["--epochs", 1, "--batch-size", 2, "--no-plots"]
LORENZ = ["generate", "lorenz", "--nodes", 3, "--trajectories", 4, "--t-end", 0.2, "--dt", 0.1]


@pytest.mark.parametrize("option", ["--lr", "--min-lr", "--clip", "--noise"])
def test_a_training_number_beyond_float32_is_refused(user_files, tmp_path, option):
    line = one_line_error(invoke("train", user_files["data"], *FAST, option, "1e39",
                                 "--run-dir", tmp_path / "r"))
    assert option.lstrip("-").replace("-", "_") in line and "float32" in line, line
    assert not (tmp_path / "r").exists()


def test_min_lr_above_lr_is_refused(user_files, tmp_path):
    for given in (["--min-lr", 1], ["--min-lr", "1e30"], ["--lr", "1e-7"]):
        line = one_line_error(invoke("train", user_files["data"], *FAST, *given,
                                     "--run-dir", tmp_path / "r"))
        assert "is above lr" in line and "--min-lr" in line, line
    assert not (tmp_path / "r").exists()


def test_wrap_angles_without_angles_is_refused_before_the_run_folder(user_files, tmp_path):
    line = one_line_error(invoke("train", user_files["data"], *FAST, "--wrap-angles",
                                 "--run-dir", tmp_path / "r"))
    assert "--wrap-angles" in line and "declares no periodic states" in line, line
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("given", [["-p", "sigma=1", "-p", "sigma=2"],
                                   ["-p", "coupling=1", "--coupling", 2]])
def test_a_system_parameter_given_twice_is_refused(tmp_path, given):
    line = one_line_error(invoke(*LORENZ, *given, "--out", tmp_path / "x.h5"))
    assert "given twice" in line, line
    assert not (tmp_path / "x.h5").exists()


def test_an_rtol_below_the_dtypes_reach_is_refused(user_files, tmp_path):
    line = one_line_error(invoke(*LORENZ, "--rtol", "1e-20", "--atol", "1e-20",
                                 "--out", tmp_path / "x.h5"))
    assert "rtol 1e-20 is below what float64 can resolve" in line and "2.2e-15" in line
    for dtype, rtol in (("float32", "1e-7"), ("float64", "1e-16")):
        line = one_line_error(invoke("train", user_files["data"], *FAST, "--dtype", dtype,
                                     "--rtol", rtol, "--run-dir", tmp_path / "r"))
        assert f"below what {dtype} can resolve" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    # Within reach, or unused by fixed steps: accepted.
    TrainConfig(dataset="d.h5", dtype="float64", solver={"rtol": 1e-7})
    TrainConfig(dataset="d.h5", solver={"rtol": 1e-12, "fixed_dt": 0.01})
    GenerateConfig(system="lorenz", solver={"rtol": 1e-14})


def test_finetune_of_one_model_into_an_ensemble_is_refused(user_files, tmp_path):
    line = one_line_error(invoke("finetune", user_files["run"], user_files["data"], *FAST,
                                 "--seeds", 3, "--run-dir", tmp_path / "r"))
    assert "holds 1 member" in line and "--seeds 1" in line, line
    assert not (tmp_path / "r").exists()


def test_a_csv_naming_a_column_twice_is_refused(user_files, tmp_path):
    rows = ["trajectory,time,node,p,p"] + [f"{k},{t / 10:.1f},{n},{k + t},{n}"
                                           for k in range(4) for t in range(3) for n in range(3)]
    (tmp_path / "s.csv").write_text("\n".join(rows) + "\n")
    line = one_line_error(invoke("import", "--states", tmp_path / "s.csv", "--edge-list",
                                 user_files["edges"], "--dt", 0.1, "--out", tmp_path / "b.h5"))
    assert "names p more than once" in line, line
    assert not (tmp_path / "b.h5").exists()


def test_states_that_never_vary_are_said(user_files, tmp_path):
    np.save(tmp_path / "ones.npy", np.ones((6, 5, 3, 2)))
    data = tmp_path / "ones.h5"
    assert invoke("import", "--states", tmp_path / "ones.npy", "--adjacency",
                  user_files["adjacency"], "--dt", 0.1, "--out", data).exit_code == 0
    result = invoke("train", data, *FAST, "--run-dir", tmp_path / "r")
    assert result.exit_code == 0, result.output
    (line,) = [x for x in result.stderr.splitlines() if x.startswith("Warning:")]
    assert "every state component is constant over the train split" in line
