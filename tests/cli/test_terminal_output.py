"""What mpnode prints survives any terminal and shell: an ASCII-only stdout, tables that fit
100 columns in a pipe, suggested commands that paste as they are, and an out-of-memory
error while writing that is one line."""

from __future__ import annotations

import os
import shlex
from pathlib import Path

from conftest import invoke, one_line_error
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.report.tables import PIPE_WIDTH
from mpnode_cli.terminal import suggested

GENERATE = ["generate", "lorenz", "--nodes", "3", "--trajectories", "8", "--t-end", "0.5"]


def test_an_ascii_only_stdout_gets_ascii(tmp_path):
    out = tmp_path / "g.h5"
    result = CliRunner(charset="ascii").invoke(app, [*GENERATE, "--out", str(out)])
    assert result.exit_code == 0, (result.output, result.exception)
    assert "lorenz on 1 x complete" in result.output  # × spelled x
    assert out.is_file()


def test_tables_fit_100_columns_off_a_terminal(tmp_path):
    listed = invoke("experiment", "list")
    generated = invoke(*GENERATE, "--out", tmp_path / ("a-long-folder-name" * 4) / "g.h5")
    for result in (listed, generated):
        assert result.exit_code == 0, result.output
        table = [line for line in result.output.splitlines() if line[:1] in "┏┃┡│└┌├"]
        assert table, result.output
        assert max(len(line) for line in table) <= PIPE_WIDTH, result.output


def test_suggested_commands_are_shell_quoted(user_files, tmp_path):
    out = tmp_path / "out dir" / "-my set.h5"
    result = invoke("import", "--states", user_files["states"], "--edge-list",
                    user_files["edges"], "--dt", "0.1", "--out", out)
    assert result.exit_code == 0, result.output
    shown = result.output.split("check it with: ")[1].splitlines()[0]
    words = shlex.split(shown)
    assert words[:2] == ["mpnode", "check"] and len(words) == 3, shown
    assert Path(words[2]) == out  # one word, the file itself
    assert suggested("check", Path("-x.h5")) == "mpnode check ./-x.h5"
    assert suggested("train", "--resume", Path("my run")) == "mpnode train --resume 'my run'"


def test_out_of_memory_while_writing_predictions_is_one_line(user_files, tmp_path,
                                                             monkeypatch):
    import numpy as np

    import mpnode_cli.training.predict as predict

    def no_memory(*args, **kwargs):
        np.empty(2**62, np.uint8)  # numpy's _ArrayMemoryError, as a real shortage raises

    monkeypatch.setattr(predict, "write_dataset", no_memory)
    out = tmp_path / "s.h5"
    line = one_line_error(invoke("simulate", user_files["checkpoint"], "--x0", user_files["x0"],
                                 "--adjacency", user_files["adjacency"], "--t-end", "0.3",
                                 "--dt", "0.1", "--out", out, "-y"))
    assert "out of memory writing the predictions" in line, line
    assert "nothing was written" in line, line
    assert os.listdir(tmp_path) == []
