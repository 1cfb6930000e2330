"""The CLI shell: help, version, and that `--help` stays free of heavy imports."""

from __future__ import annotations

import subprocess
import sys

from typer.testing import CliRunner

from mpnode_cli import __version__
from mpnode_cli.cli.app import app

runner = CliRunner()


def test_help_lists_the_verbs():
    result = runner.invoke(app, ["--help"])
    assert result.exit_code == 0
    for verb in ("generate", "import", "train", "evaluate", "zeroshot", "finetune", "info",
                 "check", "simulate"):
        assert verb in result.output


def test_version():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert __version__ in result.output


def test_help_does_not_import_torch():
    code = (
        "import sys\n"
        "from mpnode_cli.cli.app import app\n"
        "try:\n"
        "    app(['--help'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "heavy = [m for m in ('torch', 'h5py', 'matplotlib', 'scipy') if m in sys.modules]\n"
        "print('HEAVY', heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert "HEAVY []" in out
