"""Error lines that name the cause, once: the file at fault, the path once, the separator
a table uses, a folder that is not a run's, an output name that means another kind of
file, and a current folder that was deleted. And a path through a folder that does not
exist (`a/../b`) leaves no stray folder behind.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

from conftest import child_env, invoke, one_line_error


def test_a_file_that_is_not_hdf5_is_named_once(tmp_path):
    path = tmp_path / "x.h5"
    path.write_text("hi\n")
    line = one_line_error(invoke("check", path))
    assert line.count(str(path)) == 1, line


def test_a_checkpoint_of_another_model_in_a_run_is_blamed_not_its_config(own_user_files,
                                                                          tmp_path):
    other = tmp_path / "gnode"
    assert invoke("train", own_user_files["data"], "--model", "gnode", "--epochs", 1,
                  "--batch-size", 2, "--no-plots", "--run-dir", other).exit_code == 0
    run = own_user_files["run"]
    shutil.copy(other / "checkpoints" / "last.pt", run / "checkpoints" / "last.pt")
    line = one_line_error(invoke("train", "--resume", run, "--epochs", 3))
    assert f"{run}/checkpoints/last.pt is not a checkpoint of the model its config.json" \
        in line, line


def test_a_semicolon_table_is_said_to_be_one(tmp_path, user_files):
    table = tmp_path / "s.csv"
    table.write_text("trajectory;time;node;a\n0;0;0;0,1\n")
    line = one_line_error(invoke("import", "--states", table, "--edge-list",
                                 user_files["edges"], "--dt", 0.1, "--out", tmp_path / "o.h5"))
    assert "separated by ';', mpnode reads ','" in line, line


def test_a_folder_of_other_files_is_not_offered_for_a_resume(user_files, tmp_path):
    (tmp_path / "mine.txt").write_text("notes\n")
    line = one_line_error(invoke("train", user_files["data"], "--epochs", 1, "--no-plots",
                                 "--run-dir", tmp_path))
    assert "is a folder of other files, not a run folder" in line and "--resume" not in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]


def test_a_member_is_not_written_under_a_datasets_name(user_files, tmp_path):
    out = tmp_path / "m.h5"
    line = one_line_error(invoke("check", user_files["checkpoint"], "--member", 0, "--out", out))
    assert "a checkpoint is a .pt file, and .h5 names a dataset" in line, line
    assert not out.exists()


def test_a_path_through_a_missing_folder_leaves_no_stray_folder(user_files, tmp_path,
                                                               monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = invoke("train", user_files["data"], "--epochs", 1, "--no-plots", "--run-dir",
                    "a/../b/./c")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]
    assert (tmp_path / "b" / "c" / "config.json").is_file()


def test_a_deleted_current_folder_is_one_line(tmp_path):
    gone = tmp_path / "gone"
    gone.mkdir()
    code = (f"import os, sys; os.chdir({str(gone)!r}); os.rmdir({str(gone)!r}); "
            "sys.argv = ['mpnode', 'check', 'x.h5']; from mpnode_cli.cli.app import main; "
            "main()")
    done = subprocess.run([sys.executable, "-c", code], env=child_env(), capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip() == ("Error: the current folder no longer exists (it was deleted "
                                   "or moved): change to another folder and run it again")


def test_a_resume_interrupted_while_it_starts_says_the_run_is_resumable(own_user_files,
                                                                        monkeypatch):
    from mpnode_cli.training import loop

    def interrupted(*_args, **_kw):
        raise KeyboardInterrupt

    monkeypatch.setattr(loop, "set_up", interrupted)
    run = own_user_files["run"]
    result = invoke("train", "--resume", run, "--epochs", 3)
    assert result.exit_code == 130, result.output
    assert "before training started: the run folder is intact: continue it with mpnode " \
        f"train --resume {run}" in result.output, result.output
