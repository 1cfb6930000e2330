"""A system of your own (docs/custom-systems.md): the walk-through's commands run end to end
on the example file, its data agree with scipy, it installs as an entry point, and a bad
plug-in is one line and exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import doc_commands, fhn_reference, invoke

from mpnode_cli.data.hdf5 import read_dataset

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "fitzhugh_nagumo.py"
DOC = ROOT / "docs" / "custom-systems.md"
# Later options win: the walk-through at a test's size.
SMALL = {"generate": ["--trajectories", "24", "--t-end", "6"],
         "train": ["--epochs", "2", "--batch-size", "8", "--no-plots"]}


def walkthrough() -> list[list[str]]:
    """The `mpnode ...` commands of the doc's walk-through, in order."""
    text = DOC.read_text()
    section = text.split("<!-- walk-through -->")[1].split("<!-- /walk-through -->")[0]
    return [words[1:] for words in doc_commands(section) if words[0] == "mpnode"]


def test_the_walkthrough_runs_end_to_end(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "examples").mkdir()
    (tmp_path / "examples" / EXAMPLE.name).write_text(EXAMPLE.read_text())
    commands = walkthrough()
    verbs = [c[0] for c in commands]
    assert verbs[:3] == ["generate", "check", "train"] and "zeroshot" in verbs
    for args in commands:
        result = invoke(*args, *SMALL.get(args[0], []))
        assert result.exit_code == 0, (args, result.output)
    data = sorted((tmp_path / "datasets").glob("*.h5"))
    assert data and all(read_dataset(p).system == "fhn" for p in data)
    run = next((tmp_path / "runs").iterdir())
    summary = json.loads((run / "summary.json").read_text())
    assert summary["finished"] and summary["epochs"] == 2


def test_generated_data_agree_with_scipy(tmp_path):
    out = tmp_path / "f.h5"
    result = invoke("generate", "fhn", "--system-file", EXAMPLE, "--nodes", 5, "--topology",
                    "er", "--trajectories", 6, "--t-end", 10, "--dt", 0.5, "-p", "c=0.3",
                    "-p", "ic_box=1.5", "--dtype", "float64", "--out", out)
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    assert ds.scalar_params == {"a": 0.7, "b": 0.8, "eps": 0.08, "I": 0.5, "c": 0.3}
    assert ds.config["system_file"] == str(EXAMPLE) and ds.config["params"]["ic_box"] == 1.5
    assert np.abs(ds.states[:, 0]).max() <= 1.5
    for k in range(3):
        np.testing.assert_allclose(ds.states[k], fhn_reference(ds, k), atol=1e-6)


def test_an_entry_point_is_found_by_name(tmp_path, entry_point):
    entry_point("fhn", "fitzhugh_nagumo:FitzHughNagumo", EXAMPLE.parent)
    out = tmp_path / "p.h5"
    result = invoke("generate", "--preset", "fhn-chain8", "--trajectories", 8,
                    "--t-end", 2, "--out", out)
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    assert (ds.system, ds.num_nodes, ds.config["topology"]) == ("fhn", 8, "chain")
    check = invoke("check", out)
    assert check.exit_code == 0, check.output


@pytest.mark.parametrize(("source", "message"), [
    ("import numpy\n", "exactly one System subclass"),
    ("def broken(:\n", "does not import"),
    (EXAMPLE.read_text().replace('"fhn"', '"lorenz"'), "built-in system"),
    (EXAMPLE.read_text().replace('default_topology: ClassVar[str] = "chain"',
                                 'default_topology: ClassVar[str] = "ring"'), "ring"),
    (EXAMPLE.read_text().replace("    def rhs(", "    def not_rhs("), "does not declare"),
])
def test_a_bad_plugin_is_one_line(tmp_path, source, message):
    path = tmp_path / "mine.py"
    path.write_text(source)
    result = invoke("generate", "--system-file", path, "--out", tmp_path / "x.h5")
    assert result.exit_code == 2, result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error:") and message in lines[0], lines
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize(("args", "message"), [
    (["-p", "ic_box=-1"], "ic_box must be a finite number >= 0"),
    (["-p", "ic_box=wide"], "ic_box must be a number"),
    (["-p", "tau=2"], "unknown parameter 'tau' for system 'fhn'"),
    (["-p", "eps=fast"], "eps must be a finite number"),
    (["--coupling", "1"], "unknown parameter 'coupling'"),
])
def test_a_plugins_options_are_checked(tmp_path, args, message):
    result = invoke("generate", "fhn", "--system-file", EXAMPLE, *args, "--out",
                    tmp_path / "x.h5")
    assert result.exit_code == 2, result.output
    assert message in result.output, result.output


def test_a_plugin_imports_the_graph_types_and_the_neighbour_sum_where_they_were():
    """`mpnode_cli.graphs.EdgeList` (docs/custom-systems.md) and
    `mpnode_cli.systems.base.NeighbourSum` still name the types that moved into modules."""
    from mpnode_cli import graphs
    from mpnode_cli.graphs import matrices
    from mpnode_cli.systems import NeighbourSum, base, neighbour_sum

    assert (graphs.EdgeList, graphs.EdgeBatch, graphs.Graphs) == (
        matrices.EdgeList, matrices.EdgeBatch, matrices.Graphs)
    assert base.NeighbourSum is neighbour_sum.NeighbourSum is NeighbourSum
