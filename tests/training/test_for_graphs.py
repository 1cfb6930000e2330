"""`mpnode train --for-graphs`: degree-coverage data made for the targets' hubs.

The targets' in-degrees are computed here with networkx from the files' own edges, not
with `mpnode_cli.training.coverage`; the coverage data's in-degrees from the raw HDF5 edge
arrays.
"""

from __future__ import annotations

import json
import math

import h5py
import networkx as nx
import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.training.coverage import in_degrees

N_SOURCE = 6


def _gen(out, nodes, k, *extra):
    result = invoke("generate", "sis", "--nodes", nodes, "--topology", "ba", "--trajectories",
                    k, "--t-end", 0.4, "--dt", 0.1, *extra, "-o", out)
    assert result.exit_code == 0, result.output
    return out


def _file_in_degrees(path) -> np.ndarray:
    """Every node's in-degree in every graph of a dataset, from its raw edge arrays (an
    edge of multiplicity w is stored w times)."""
    with h5py.File(path, "r") as f:
        receivers = f["graph/edges"][1].astype(np.int64)
        counts = f["graph/num_edges"][()]
        n = f["states"].shape[2]
    graph = np.repeat(np.arange(len(counts)), counts)
    return np.bincount(graph * n + receivers, minlength=len(counts) * n)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("for-graphs")
    return {"source": _gen(folder / "src.h5", N_SOURCE, 12, "--graphs", 2),
            "target": _gen(folder / "tgt.h5", 30, 2, "--graph-seed", 7)}


def test_in_degrees_of_every_kind_of_target_agree_with_networkx(tmp_path, data):
    rng = np.random.default_rng(3)
    a = (rng.random((2, 9, 9)) < 0.4).astype(np.uint8)
    np.save(tmp_path / "a.npy", a)
    expected = [d for g in a for _, d in sorted(nx.DiGraph(g.T).in_degree())]
    np.testing.assert_array_equal(in_degrees(tmp_path / "a.npy"), expected)
    edges = tmp_path / "edges.txt"
    edges.write_text("0 1\n1 2\n2 0\n0 3\n")
    g = nx.Graph([(0, 1), (1, 2), (2, 0), (0, 3)])
    np.testing.assert_array_equal(in_degrees(edges), [g.degree[v] for v in range(4)])
    np.testing.assert_array_equal(in_degrees(data["target"]),
                                  _file_in_degrees(data["target"]))


def test_a_multigraphs_hubs_count_every_parallel_edge(tmp_path):
    out = _gen(tmp_path / "hubs.h5", 8, 3, "--graphs", 3, "--hubs", 2,
               "--hub-multiplicity", 4)
    # The last graph's hubs hear every other node 4 times: in-degree 4·(N − 1).
    assert in_degrees(out).max() == 4 * 7
    np.testing.assert_array_equal(in_degrees(out), _file_in_degrees(out))


def test_for_graphs_trains_on_coverage_that_reaches_the_targets_hubs(tmp_path, data):
    run = tmp_path / "run"
    result = invoke("train", data["source"], "--for-graphs", data["target"], "--epochs", 1,
                    "--run-dir", run, "--no-plots")
    assert result.exit_code == 0, result.output
    config = json.loads((run / "config.json").read_text())
    coverage = run / "coverage.h5"
    assert [str(p) for p in config["dataset"]] == [str(data["source"].resolve()),
                                                    str(coverage.resolve())]
    reach = int(_file_in_degrees(data["target"]).max())
    w = math.ceil(reach / (N_SOURCE - 1))  # the least W with W·(N − 1) ≥ reach
    assert config["coverage"]["max_in_degree"] == reach
    assert config["coverage"]["multiplicity"] == w
    assert _file_in_degrees(coverage).max() == w * (N_SOURCE - 1) >= reach
    # The transfer recipe, where nothing was given.
    assert (config["schedule"], config["clip"], config["stop_patience"]) == ("cosine", 5.0, None)
    with h5py.File(coverage, "r") as cov, h5py.File(data["source"], "r") as src:
        made, source = (json.loads(f.attrs["config"]) for f in (cov, src))
    for key in ("system", "params", "nodes", "t_end", "dt", "solver", "topology"):
        assert made[key] == source[key], key
    assert made["seed"] != source["seed"]
    assert f"in-degree covered by training: 1–{w * (N_SOURCE - 1)}" in result.output


def test_options_given_win_over_the_transfer_recipe(tmp_path, data):
    run = tmp_path / "run"
    result = invoke("train", data["source"], "--for-in-degree", 12, "--epochs", 1,
                    "--clip", 3, "--run-dir", run, "--no-plots")
    assert result.exit_code == 0, result.output
    config = json.loads((run / "config.json").read_text())
    assert (config["schedule"], config["clip"]) == ("cosine", 3.0)
    assert config["coverage"]["multiplicity"] == math.ceil(12 / (N_SOURCE - 1))


def test_what_cannot_be_covered_is_refused_in_one_line_and_leaves_no_folder(tmp_path, data):
    run = tmp_path / "run"
    states = tmp_path / "states.npy"
    np.save(states, np.random.default_rng(0).random((6, 5, 4, 1)))
    np.save(tmp_path / "ring.npy", np.roll(np.eye(4, dtype=np.uint8), 1, axis=1))
    imported = tmp_path / "imported.h5"
    assert invoke("import", "--states", states, "--adjacency", tmp_path / "ring.npy",
                  "--dt", 0.1, "--out", imported).exit_code == 0
    cases = [
        (imported, "--for-in-degree", 10, "no simulator"),
        (data["source"], "--for-in-degree", 10**6, "above the 255"),
        (data["source"], "--for-graphs", tmp_path / "missing.h5", "does not exist"),
        (data["source"], "--seeds", 2, "--for-in-degree", 10, "one run per --seed"),
    ]
    for source, *options, said in cases:
        result = invoke("train", source, *options, "--epochs", 1, "--run-dir", run)
        assert said in one_line_error(result), result.output
        assert not run.exists()


def test_an_interrupt_while_making_the_coverage_leaves_no_folder(tmp_path, data, monkeypatch):
    import mpnode_cli.data.generate as generating

    def interrupted(config, **_):
        config.out.write_bytes(b"half a file")
        raise KeyboardInterrupt

    monkeypatch.setattr(generating, "generate", interrupted)
    run = tmp_path / "run"
    result = invoke("train", data["source"], "--for-in-degree", 10, "--run-dir", run)
    assert result.exit_code == 130, result.output
    assert not run.exists()
