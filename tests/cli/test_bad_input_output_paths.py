"""Output paths that cannot be used are refused first, in one `Error:` line that says why.

`experiment run` with an unwritable `--work` gave a traceback, and with an unwritable `--out`
one after every step had run. A run folder name over 255 bytes gave a traceback, and so did
a default run folder named after a long dataset name. Other long names were refused as
"unreadable ... even with --force", which sent the user after the wrong flag, and a name
near the limit failed at the end, when its temporary name (longer) was made. Every writer
now checks its output with the one guard (`mpnode_cli.paths`): the length of each name and
of the whole path against the filesystem's limits, and the folder's writability, before
any work.
"""

from __future__ import annotations

import os
import shutil

import pytest
from conftest import invoke, one_line_error

from mpnode_cli.experiments import scheduler as experiment_schedule

LONG = "n" * 300  # over the 255 bytes of one name on Linux and macOS filesystems


@pytest.fixture
def no_steps(monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("a step ran although the output folders cannot be written")

    monkeypatch.setattr(experiment_schedule, "run_step", never)


@pytest.mark.parametrize("option", ["--work", "--out"])
def test_experiment_folders_are_checked_before_any_step(tmp_path, no_steps, option):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    folders = {"--work": tmp_path / "work", "--out": tmp_path / "reports"}
    for bad in (blocker, blocker / "below"):
        folders[option] = bad
        line = one_line_error(invoke("experiment", "run", "zeroshot-lorenz", "--scale", "tiny",
                                     "--work", folders["--work"], "--out", folders["--out"]))
        assert "a-file" in line and "folder" in line
    assert blocker.read_text() == "not a folder"


def _writers(f, tmp_path, name):
    """Every verb that writes, with `name` (a path under tmp_path) as its output."""
    return {
        "generate": ["generate", "lorenz", "--nodes", 3, "--trajectories", 2, "--t-end", 0.2,
                     "--dt", 0.1, "--out", name],
        "generate --shard": ["generate", "lorenz", "--nodes", 3, "--trajectories", 4,
                             "--t-end", 0.2, "--dt", 0.1, "--chunk-size", 2, "--shard", "0/2",
                             "--out", name],
        "import": ["import", "--states", f["states"], "--adjacency", f["adjacency"], "--dt",
                   0.1, "--out", name],
        "simulate": ["simulate", f["run"], "--x0", f["x0"], "--adjacency", f["adjacency"],
                     "--t-end", 0.2, "--dt", 0.1, "--out", name],
        "evaluate --save-predictions": ["evaluate", f["run"], f["data"], "--split", "all",
                                        "--save-predictions", name],
        "evaluate --plot-dir": ["evaluate", f["run"], f["data"], "--plot", "--plot-dir", name],
        "train --run-dir": ["train", f["data"], "--epochs", 1, "--no-plots", "--run-dir",
                            name],
        "experiment --work": ["experiment", "run", "zeroshot-lorenz", "--scale", "tiny",
                              "--work", name, "--out", tmp_path / "reports"],
    }


VERBS = ["generate", "import", "simulate", "evaluate --save-predictions",
         "evaluate --plot-dir", "train --run-dir", "experiment --work"]


@pytest.mark.parametrize("verb", VERBS)
def test_a_name_too_long_is_refused_as_such(user_files, tmp_path, no_steps, verb):
    line = one_line_error(invoke(*_writers(user_files, tmp_path, tmp_path / LONG)[verb]))
    assert "300 bytes, longer than the 255" in line and "--force" not in line
    assert os.listdir(tmp_path) == []


def test_a_shard_name_too_long_is_refused_as_such(user_files, tmp_path):
    """The name given fits; the shard's, `<stem>.shard-0000-of-0002.h5`, does not."""
    out = tmp_path / ("n" * 240 + ".h5")
    line = one_line_error(invoke(*_writers(user_files, tmp_path, out)["generate --shard"]))
    assert "262 bytes, longer than the 255" in line and "--force" not in line


@pytest.mark.parametrize("verb", ["import", "train --run-dir", "experiment --work"])
def test_a_path_too_long_is_refused_as_such(user_files, tmp_path, no_steps, verb):
    deep = tmp_path.joinpath(*["d" * 200] * 21, "out.h5")  # each name fits, not the whole
    line = one_line_error(invoke(*_writers(user_files, tmp_path, deep)[verb]))
    assert "full path" in line and "--force" not in line
    assert os.listdir(tmp_path) == []


def test_a_name_near_the_limit_is_written(user_files, tmp_path):
    """Its temporary name beside it is shortened to fit, not refused by the filesystem."""
    out = tmp_path / ("n" * 250 + ".h5")
    result = invoke(*_writers(user_files, tmp_path, out)["import"])
    assert result.exit_code == 0, result.output
    assert os.listdir(tmp_path) == [out.name]


def test_a_default_run_folder_fits_a_long_dataset_name(user_files, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    data = tmp_path / ("n" * 250 + ".h5")
    shutil.copy(user_files["data"], data)  # a copy: a link would resolve to its target
    result = invoke("train", data, "--epochs", 1, "--batch-size", 2, "--no-plots")
    assert result.exit_code == 0, result.output
    (run,) = (tmp_path / "runs").iterdir()
    assert len(os.fsencode(run.name)) <= 255 and (run / "summary.json").is_file()
