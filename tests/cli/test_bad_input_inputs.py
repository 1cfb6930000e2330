"""An output is never one of its verb's inputs: one `Error:` line and exit 2, even with
`--force`, and the input left as it was.

`evaluate --save-predictions DATA.h5 --force` used to replace the ground truth it had just
been evaluated on, `simulate --out` the checkpoint or the initial states, `import --out` the
states, all with exit 0; only `merge` compared paths, and not through hard links. Every
writer now asks the one guard (`mpnode_cli.paths.check_not_input`), which compares files,
not spellings: through symbolic and hard links.
"""

from __future__ import annotations

import hashlib
import os

import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate

SIMULATE = ["--t-end", "0.2", "--dt", "0.1"]


def digest(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def refused_and_kept(target, *args) -> str:
    """Run a verb that would write over `target`; check that it refused and kept it."""
    before = digest(target)
    line = one_line_error(invoke(*args))
    assert "one of the inputs" in line, line
    assert digest(target) == before
    return line


@pytest.mark.parametrize("target", ["data", "checkpoint"])
def test_evaluate_never_saves_predictions_over_its_inputs(own_user_files, target):
    f = own_user_files
    line = refused_and_kept(f[target], "evaluate", f["run"], f["data"], "--split", "all",
                            "--save-predictions", f[target], "--force")
    assert line.startswith("Error: --save-predictions:")


@pytest.mark.parametrize("target", ["checkpoint", "x0", "adjacency"])
def test_simulate_never_writes_over_its_inputs(own_user_files, target):
    f = own_user_files
    refused_and_kept(f[target], "simulate", f["run"], "--x0", f["x0"], "--adjacency",
                     f["adjacency"], *SIMULATE, "--out", f[target], "--force")


def test_simulate_never_writes_over_its_edge_list(own_user_files):
    f = own_user_files
    refused_and_kept(f["edges"], "simulate", f["checkpoint"], "--x0", f["x0"], "--edge-list",
                     f["edges"], *SIMULATE, "--out", f["edges"], "--force")


@pytest.mark.parametrize("target", ["states", "adjacency"])
def test_import_never_writes_over_its_inputs(own_user_files, target):
    f = own_user_files
    refused_and_kept(f[target], "import", "--states", f["states"], "--adjacency",
                     f["adjacency"], "--dt", 0.1, "--out", f[target], "--force")


def test_an_input_under_another_name_is_still_an_input(own_user_files, tmp_path):
    """A symbolic link to an input, and a hard link (the same file under two names)."""
    f = own_user_files
    soft = tmp_path / "soft.npy"
    soft.symlink_to(f["x0"])
    hard = tmp_path / "hard.npy"
    os.link(f["states"], hard)
    refused_and_kept(f["x0"], "simulate", f["run"], "--x0", soft, "--adjacency",
                     f["adjacency"], *SIMULATE, "--out", f["x0"], "--force")
    refused_and_kept(f["states"], "import", "--states", f["states"], "--adjacency",
                     f["adjacency"], "--dt", 0.1, "--out", hard, "--force")


def test_generate_never_writes_over_its_edge_list(own_user_files):
    f = own_user_files
    refused_and_kept(f["edges"], "generate", "kuramoto", "--nodes", 3, "--trajectories", 2,
                     "--t-end", 0.2, "--dt", 0.1, "--edge-list", f["edges"], "--out",
                     f["edges"], "--force")


def test_merge_never_writes_over_a_shard_through_a_hard_link(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fields = {"system": "lorenz", "nodes": 3, "trajectories": 4, "t_end": 0.2, "dt": 0.1,
              "chunk_size": 2, "out": "d.h5"}
    shards = [generate(GenerateConfig(**fields, shard=(i, 2))).path for i in range(2)]
    os.link(shards[0], tmp_path / "merged.h5")
    refused_and_kept(shards[0], "merge", *shards, "-o", tmp_path / "merged.h5", "--force")
