"""Nothing the user asked for is quietly done otherwise.

The defects as a user met them: `train --trajectories 10000` on 28 train trajectories ran
without a word; `generate lorenz --grid 3` made a 9-node Lorenz, though a grid means
nothing there; a dataset with 0 validation trajectories (`--split 1,0,0`, K = 1, a tiny
K) was written without a warning. Now: a warning line saying how many trajectories train
uses; `--grid` refused in one line by every system that does not declare a grid layout
(`System.grid_layout`); a warning line from generate and import for an empty split, and a
one-line refusal with the counts from train.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.generate import generate
from mpnode_cli.systems.registry import SYSTEMS

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "fitzhugh_nagumo.py"
SMALL = ["--t-end", "0.2", "--dt", "0.1"]
FAST = ["--epochs", "1", "--batch-size", "8", "--no-plots"]


def warnings(result) -> list[str]:
    assert result.exit_code == 0, result.output
    return [line for line in result.stderr.splitlines() if line.startswith("Warning:")]


@pytest.fixture(scope="module")
def lorenz(tmp_path_factory):
    """Lorenz, N = 2: 28 trajectories (20 train), and 3 (2 train, 0 validation)."""
    root = tmp_path_factory.mktemp("surprises")
    small = {"system": "lorenz", "nodes": 2, "t_end": 0.2, "dt": 0.1}
    return {k: generate(GenerateConfig(**small, trajectories=k, out=root / f"l{k}.h5")).path
            for k in (28, 3)}


@pytest.mark.parametrize("verb", ["train", "finetune"])
def test_more_trajectories_than_the_train_split_is_said(lorenz, tmp_path, verb):
    start = []
    if verb == "finetune":
        assert invoke("train", lorenz[28], *FAST, "--run-dir", tmp_path / "p").exit_code == 0
        start = [tmp_path / "p"]
    result = invoke(verb, *start, lorenz[28], *FAST, "--trajectories", 10000,
                    "--run-dir", tmp_path / "r")
    (line,) = warnings(result)
    assert "--trajectories 10000" in line and "l28.h5 has 20 train trajectories" in line
    # Asked for no more than there are: no word.
    result = invoke(verb, *start, lorenz[28], *FAST, "--trajectories", 20,
                    "--run-dir", tmp_path / "r2")
    assert warnings(result) == []
    shown = " ".join(invoke(verb, "--help").output.replace("│", " ").split())
    assert "with a warning, where a dataset has fewer" in shown


# Of the built-in systems, gene alone lays its nodes on a grid (`System.grid_layout`).
NO_GRID = sorted(set(SYSTEMS) - {"gene"})


@pytest.mark.parametrize("system", [*NO_GRID, "fhn"])
def test_grid_is_refused_where_it_means_nothing(tmp_path, system):
    own = ["--system-file", EXAMPLE] if system == "fhn" else []
    out = tmp_path / "x.h5"
    line = one_line_error(invoke("generate", system, *own, "--grid", 3, "--trajectories", 4,
                                 *SMALL, "-o", out))
    assert "grid" in line and "--nodes 9" in line and not out.exists()
    # gene lays its nodes on the grid (its hot-spot initial states): it still takes --grid.
    assert SYSTEMS["gene"].grid_layout and not any(SYSTEMS[n].grid_layout for n in NO_GRID)
    result = invoke("generate", "gene", "--grid", 2, "--init", "hotspot", "--topology", "er",
                    "--trajectories", 20, *SMALL, "-o", tmp_path / "g.h5")
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize(("k", "split", "empty"), [
    (20, "1,0,0", "0 validation and 0 test"), (1, None, "0 validation and 0 test"),
    (3, None, "0 validation trajectories"), (20, "0,0.5,0.5", "0 train")])
def test_generate_warns_of_an_empty_split(tmp_path, k, split, empty):
    args = ["generate", "lorenz", "--nodes", 2, "--trajectories", k, *SMALL, "--json",
            "-o", tmp_path / "d.h5", *(["--split", split] if split else [])]
    result = invoke(*args)
    (line,) = warnings(result)
    assert empty in line and f"{k} trajectories" in line
    counts = json.loads(result.stdout)["split"]  # the warning stays off stdout
    assert sum(counts.values()) == k and 0 in counts.values()


def test_import_warns_of_an_empty_split(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "s.npy", rng.normal(size=(4, 5, 3, 2)))
    np.save(tmp_path / "a.npy", np.ones((3, 3)) - np.eye(3))
    result = invoke("import", "--states", tmp_path / "s.npy", "--adjacency",
                    tmp_path / "a.npy", "--dt", 0.1, "--split", "1,0,0",
                    "--out", tmp_path / "d.h5")
    (line,) = warnings(result)
    assert "0 validation and 0 test" in line


def test_train_without_validation_trajectories_says_so(lorenz, tmp_path):
    line = one_line_error(invoke("train", lorenz[3], *FAST, "--run-dir", tmp_path / "r"))
    assert "2 train and 0 validation trajectories" in line
    assert not (tmp_path / "r").exists()
