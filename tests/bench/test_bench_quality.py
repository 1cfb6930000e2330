"""bench/quality.py --extra: the paper's cases under a variant of the recipe."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_extra_options_reach_the_training_and_the_table_names_them(tmp_path):
    """One case at the smoke scale (one epoch) with `--extra "--clip 5"`: the run's own
    resolved config holds the clip (the CLI's default is 500), its result and the table's
    case line list the option, and the table's command reads back as the one that ran."""
    out = tmp_path / "quality.md"
    cmd = [sys.executable, str(ROOT / "bench" / "quality.py"), "--scale", "0.003",
           "--only", "kuramoto-m3", "--workers", "1", "--extra", "--clip 5",
           "--runs", str(tmp_path / "runs"), "--out", str(out)]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run(cmd, cwd=ROOT, env=env, check=True, capture_output=True, timeout=300)
    (case,) = (tmp_path / "runs").glob("case-kuramoto-m3-*/")  # the engine's step folder
    assert json.loads((case / "run" / "config.json").read_text())["clip"] == 5.0
    record = json.loads((case / "step.json").read_text())  # the engine's record
    assert record["result"]["options"] == ["--message-dim", "3", "--clip", "5"]
    text = out.read_text()
    assert "`mpnode train kuramoto10-ba.h5 --message-dim 3 --clip 5`" in text
    shown = text.split("Command: `", 1)[1].split("`", 1)[0]
    words = shlex.split(shown)
    assert words[words.index("--extra") + 1] == "--clip 5"
