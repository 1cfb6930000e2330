"""Two runs writing one new output without `--force`: the second is refused (one `Error:`
line, exit 2) and the first's file stands.

`import`, `merge` and `simulate` used to check the output once, then work, then rename over
whatever was there by then: both runs exited 0 and the last silently replaced the first.
Every writer now reserves its output before the work (`mpnode_cli.paths.reserve_output`:
created exclusively, an empty placeholder until the finished file is renamed over it).
Each test starts the second run, the real CLI in a subprocess, while the first (in this
process) is at work.
"""

from __future__ import annotations

import subprocess
import sys

import h5py
import numpy as np
from conftest import child_env, invoke

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data import importers, shards
from mpnode_cli.data.generate import generate
from mpnode_cli.training import simulate


def meanwhile(monkeypatch, module, name: str, *args) -> list[subprocess.CompletedProcess]:
    """Make `module.name` first run `mpnode ARGS` in another process, to the end; the
    list it returns fills with that run's result."""
    done: list[subprocess.CompletedProcess] = []
    original = getattr(module, name)

    def racing(*a, **kw):
        if not done:
            done.append(subprocess.run(
                [sys.executable, "-m", "mpnode_cli", *map(str, args)], capture_output=True,
                text=True, env=child_env(MPNODE_THREADS="1"), timeout=300))
        return original(*a, **kw)

    monkeypatch.setattr(module, name, racing)
    return done


def assert_refused(done: list[subprocess.CompletedProcess]) -> None:
    """The second run: refused in one line, because the first holds the output."""
    (second,) = done
    assert second.returncode == 2, second.stdout + second.stderr
    lines = second.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:"), second.stderr
    assert "already exists and is empty: another mpnode run may be writing it" in lines[0]


def test_two_imports_to_one_new_file(user_files, tmp_path, monkeypatch):
    f, out = user_files, tmp_path / "d.h5"
    common = ["--states", f["states"], "--adjacency", f["adjacency"], "--out", out]
    done = meanwhile(monkeypatch, importers, "load_states", "import", *common, "--dt", 0.2)
    first = invoke("import", *common, "--dt", 0.1)
    assert first.exit_code == 0, first.output
    assert_refused(done)
    with h5py.File(out, "r") as written:
        assert written.attrs["dt"] == 0.1  # the first run's
    # A run that fails after taking its output leaves nothing: no file, no folder made.
    (tmp_path / "bad.npy").write_text("not numpy")
    monkeypatch.undo()
    assert invoke("import", "--states", tmp_path / "bad.npy", "--adjacency", f["adjacency"],
                  "--dt", 0.1, "--out", tmp_path / "new" / "never.h5").exit_code == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npy", "d.h5"]


def test_two_simulates_to_one_new_file(user_files, tmp_path, monkeypatch):
    f, out = user_files, tmp_path / "p.h5"
    common = [f["run"], "--x0", f["x0"], "--adjacency", f["adjacency"], "--dt", 0.1, "--out",
              out]
    done = meanwhile(monkeypatch, simulate, "roll_out", "simulate", *common, "--t-end", 0.3)
    first = invoke("simulate", *common, "--t-end", 0.2)
    assert first.exit_code == 0, first.output
    assert_refused(done)
    with h5py.File(out, "r") as written:
        np.testing.assert_allclose(written["time"][()], [0.0, 0.1, 0.2])  # the first run's


def test_two_merges_to_one_new_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fields = {"system": "lorenz", "nodes": 3, "trajectories": 4, "t_end": 0.2, "dt": 0.1,
              "chunk_size": 2, "out": "d.h5"}
    parts = [generate(GenerateConfig(**fields, shard=(i, 2))).path for i in range(2)]
    done = meanwhile(monkeypatch, shards, "_copy", "merge", *parts, "-o", "m.h5", "--virtual")
    first = invoke("merge", *parts, "-o", "m.h5")
    assert first.exit_code == 0, first.output
    assert_refused(done)
    with h5py.File("m.h5", "r") as written:
        assert not written["states"].is_virtual  # the first run's copy
