"""Each verb's happy path writes only what it says it wrote: the folder it runs in is walked
before and after, and every file created or changed must be one its output line names (or
lie in the run folder it names)."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from conftest import invoke

GENERATE = ["generate", "lorenz", "--nodes", "3", "--trajectories", "8", "--t-end", "0.2",
            "--dt", "0.05", "--chunk-size", "4"]


def snapshot(root: Path) -> dict[str, str]:
    """Every file under `root` (relative path → sha256 of its bytes)."""
    files = {}
    for folder, _, names in os.walk(root):
        for name in names:
            path = Path(folder, name)
            files[str(path.relative_to(root))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return files


def test_every_verb_writes_only_what_it_names(own_user_files, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    files = {k: str(Path(v).relative_to(tmp_path)) for k, v in own_user_files.items()}
    ckpt, data = files["checkpoint"], files["data"]
    steps = [  # (arguments, what it writes: a file or a folder, named in its output)
        ([*GENERATE, "--out", "g.h5"], "g.h5"),
        ([*GENERATE, "--out", "sh.h5", "--shard", "0/2"], "sh.shard-0000-of-0002.h5"),
        ([*GENERATE, "--out", "sh.h5", "--shard", "1/2"], "sh.shard-0001-of-0002.h5"),
        (["merge", "sh.shard-0000-of-0002.h5", "sh.shard-0001-of-0002.h5", "--out", "m.h5"],
         "m.h5"),
        (["import", "--states", files["states"], "--edge-list", files["edges"], "--dt", "0.1",
          "--out", "i.h5"], "i.h5"),
        (["train", "i.h5", "--epochs", "1", "--batch-size", "2", "--no-plots", "--run-dir",
          "r"], "r"),
        (["finetune", ckpt, data, "--epochs", "1", "--batch-size", "2", "--no-plots",
          "--run-dir", "f"], "f"),
        (["evaluate", ckpt, data, "--split", "all", "--save-predictions", "p.h5"], "p.h5"),
        (["zeroshot", ckpt, "i.h5"], None),
        (["simulate", ckpt, "--x0", files["x0"], "--adjacency", files["adjacency"],
          "--t-end", "0.3", "--dt", "0.1", "--out", "s.h5"], "s.h5"),
        (["info", "m.h5"], None),
        (["check", "s.h5"], None),
    ]
    for args, writes in steps:
        before = snapshot(tmp_path)
        result = invoke(*args)
        assert result.exit_code == 0, (args, result.output)
        after = snapshot(tmp_path)
        changed = {path for path in after if before.get(path) != after[path]}
        changed |= set(before) - set(after)  # nothing may go either
        if writes is None:
            assert changed == set(), (args, changed)
            continue
        assert writes in result.output, (args, result.output)
        outside = {p for p in changed if p != writes and not p.startswith(writes + os.sep)}
        assert outside == set(), (args, outside)
        assert changed, (args, "wrote nothing")
