"""The thread policy: `--threads` beats `MPNODE_THREADS` beats one; the CLI applies it."""

from __future__ import annotations

import subprocess
import sys

import pytest
import torch
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.threads import ENV_VAR, ThreadChoice, choose_threads

runner = CliRunner()
TINY = ["lorenz", "--nodes", "2", "--trajectories", "2", "--t-end", "0.1", "--dt", "0.05"]


def test_flag_beats_variable_beats_default():
    assert choose_threads("3", {ENV_VAR: "2"}) == ThreadChoice(3, "--threads")
    assert choose_threads(None, {ENV_VAR: " 2 "}) == ThreadChoice(2, ENV_VAR)
    assert choose_threads(None, {}) == ThreadChoice(1, "default")
    assert choose_threads(None, {ENV_VAR: ""}) == ThreadChoice(1, "default")  # set but empty
    assert choose_threads(4, {ENV_VAR: "bad"}).count == 4  # an overridden variable is unread


@pytest.mark.parametrize("value", ["0", "-1", "1.5", "two", " "])
def test_bad_values_name_their_source(value):
    with pytest.raises(ValueError, match=f"--threads must be a whole number ≥ 1, got '{value}'"):
        choose_threads(value, {})
    if value.strip():
        with pytest.raises(ValueError, match=f"{ENV_VAR} must be a whole number ≥ 1"):
            choose_threads(None, {ENV_VAR: value})


def test_describe_says_how_to_change_the_default():
    assert ThreadChoice(1, "default").describe() == (
        "1 (default: one per process; --threads or MPNODE_THREADS to change)")
    assert ThreadChoice(2, ENV_VAR).describe() == "2 (from MPNODE_THREADS)"


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize(("args", "env", "expected"), [
    (["--threads", "2"], {ENV_VAR: "1"}, "2 (from --threads)"),
    ([], {ENV_VAR: "2"}, "2 (from MPNODE_THREADS)"),
    ([], {ENV_VAR: None}, "1 (default: one per process"),
])
def test_generate_sets_torch_threads(tmp_path, restore_threads, args, env, expected):
    torch.set_num_threads(3 - int(expected[0]))  # the other count, so a change shows
    result = runner.invoke(app, [*args, "generate", *TINY, "--out", str(tmp_path / "d.h5")],
                           env=env)
    assert result.exit_code == 0, result.output
    assert torch.get_num_threads() == int(expected[0])
    assert expected in result.stdout


def test_a_verbs_own_option_wins_over_the_roots(tmp_path, restore_threads):
    torch.set_num_threads(1)
    result = runner.invoke(app, ["--threads", "1", "generate", *TINY, "--out",
                                 str(tmp_path / "d.h5"), "--threads", "2"])
    assert result.exit_code == 0, result.output
    assert torch.get_num_threads() == 2
    bad = runner.invoke(app, ["generate", *TINY, "--out", str(tmp_path / "e.h5"),
                              "--threads", "0"])
    assert bad.exit_code == 2 and "--threads must be a whole number" in bad.stderr


@pytest.mark.parametrize(("args", "env", "named"), [
    (["--threads", "0"], {}, "--threads"),
    ([], {ENV_VAR: "all"}, ENV_VAR),
])
def test_cli_refuses_a_bad_count_in_one_line(tmp_path, args, env, named):
    out = tmp_path / "d.h5"
    result = runner.invoke(app, [*args, "generate", *TINY, "--out", str(out)], env=env)
    assert result.exit_code == 2, result.output
    assert result.stderr.strip().splitlines() == [
        f"Error: {named} must be a whole number ≥ 1, got {env.get(ENV_VAR, '0')!r}"]
    assert not out.exists()


def test_help_of_a_verb_ignores_a_bad_setting():
    result = runner.invoke(app, ["--threads", "0", "generate", "--help"])
    assert result.exit_code == 0 and "--preset" in result.output


def test_a_verbs_help_still_imports_no_torch():
    code = ("import sys\nfrom mpnode_cli.cli.app import app\n"
            "try:\n    app(['--threads', '2', 'train', '--help'])\nexcept SystemExit:\n    pass\n"
            "print(sorted({'torch', 'h5py'} & set(sys.modules)))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip().splitlines()[-1] == "[]"
