"""`python -m mpnode_cli` is the `mpnode` command (what `torchrun -m mpnode_cli` starts)."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import child_env


def test_python_dash_m_mpnode_cli_is_the_cli():
    out = subprocess.run([sys.executable, "-m", "mpnode_cli", "--help"],
                         env=child_env(), capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "Usage: mpnode" in out.stdout and "finetune" in out.stdout
    version = subprocess.run([sys.executable, "-m", "mpnode_cli", "--version"],
                             env=child_env(), capture_output=True,
                             text=True, timeout=60)
    assert version.returncode == 0 and version.stdout.startswith("mpnode ")


def test_a_stdout_that_cannot_be_written_is_one_line(user_files):
    """`mpnode info d.h5 > /dev/full`: one line, no traceback; a closed pipe: quiet."""
    for json_out in ([], ["--json"]):
        with open("/dev/full", "w") as full:
            out = subprocess.run([sys.executable, "-m", "mpnode_cli", "info",
                                  str(user_files["data"]), *json_out], env=child_env(),
                                 stdout=full, stderr=subprocess.PIPE, text=True, timeout=60)
        assert out.returncode == 2, out.stderr
        assert out.stderr == "Error: cannot write to standard output: No space left on device\n"
    closed = subprocess.Popen([sys.executable, "-m", "mpnode_cli", "info",
                               str(user_files["data"]), "--json"], env=child_env(),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    closed.stdout.close()  # the reader is gone before anything is written
    assert closed.wait(timeout=60) == 1 and closed.stderr.read() == ""


def test_ctrl_c_while_the_cli_is_imported_is_one_line(monkeypatch, capsys):
    """A SIGINT in the first tenths of a second lands in the import of the CLI."""
    import importlib.abc

    from mpnode_cli import __main__ as entry

    class Interrupting(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name == "mpnode_cli.cli.app":
                raise KeyboardInterrupt
            return None

    monkeypatch.delitem(sys.modules, "mpnode_cli.cli.app", raising=False)
    monkeypatch.setattr(sys, "meta_path", [Interrupting(), *sys.meta_path])
    with pytest.raises(SystemExit) as stopped:
        entry.main()
    assert stopped.value.code == 130
    assert capsys.readouterr().err == "Interrupted (SIGINT): nothing done\n"
