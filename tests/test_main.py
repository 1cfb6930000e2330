"""`python -m mpnode_cli` is the `mpnode` command (what `torchrun -m mpnode_cli` starts)."""

from __future__ import annotations

import subprocess
import sys

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
