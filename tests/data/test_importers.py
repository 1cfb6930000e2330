"""`mpnode import`: a user's arrays read back equal, graphs as the format states, and one
line with exit 2 for every input that cannot be used."""

from __future__ import annotations

import csv
import hashlib
import json

import h5py
import numpy as np
import pytest
from conftest import invoke

from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.data.validate import check_dataset

K, T, N, D = 6, 5, 4, 2


def one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("Error:"), result.output
    return lines[0]


@pytest.fixture
def arrays(tmp_path):
    rng = np.random.default_rng(0)
    states = rng.normal(size=(K, T, N, D))
    ring = np.roll(np.eye(N, dtype=np.uint8), 1, axis=1) + np.roll(np.eye(N, dtype=np.uint8),
                                                                   -1, axis=1)
    np.save(tmp_path / "s.npy", states)
    np.save(tmp_path / "a.npy", ring)
    return tmp_path, states, ring


def test_npy_and_adjacency_read_back_equal(arrays):
    root, states, ring = arrays
    out = root / "d.h5"
    result = invoke("import", "--states", root / "s.npy", "--adjacency", root / "a.npy",
                    "--dt", 0.25, "--dtype", "float64", "--state-names", "p,q", "--out", out,
                    "--seed", 3, "--json")
    assert result.exit_code == 0, result.output
    assert check_dataset(out).ok
    ds = read_dataset(out)
    np.testing.assert_array_equal(ds.states, states)
    np.testing.assert_array_equal(ds.adjacency[ds.graph_index], np.broadcast_to(ring, (K, N, N)))
    np.testing.assert_allclose(ds.time, np.arange(T) * 0.25, rtol=0, atol=1e-15)
    assert (ds.system, ds.state_names, ds.seed) == ("custom", ("p", "q"), 3)
    assert sorted(np.bincount(ds.split, minlength=3)) == sorted([4, 1, 1])  # round(0.7·6)=4
    # Provenance: the resolved config and each input's sha256; the fingerprint is training's.
    assert ds.config["verb"] == "import" and ds.config["dt"] == 0.25
    sha = hashlib.sha256((root / "s.npy").read_bytes()).hexdigest()
    assert ds.config["sources"]["states"]["sha256"] == sha
    summary = json.loads(result.output)
    assert ds.extra_attrs["fingerprint"] == summary["fingerprint"] == TrajectoryData.load(
        out).fingerprint


def test_check_finds_data_changed_after_import(arrays):
    root, _, _ = arrays
    out = root / "t.h5"
    assert invoke("import", "--states", root / "s.npy", "--adjacency", root / "a.npy", "--dt",
                  0.1, "--out", out).exit_code == 0
    with h5py.File(out, "r+") as f:
        f["states"][0, 1, 0, 0] += 1.0
    report = check_dataset(out)
    assert len(report.problems) == 1 and "fingerprint" in report.problems[0]


def test_float32_storage_is_the_cast(arrays):
    root, states, _ = arrays
    out = root / "d32.h5"
    assert invoke("import", "--states", root / "s.npy", "--adjacency", root / "a.npy", "--dt",
                  0.1, "--out", out).exit_code == 0
    np.testing.assert_array_equal(read_dataset(out).states, states.astype(np.float32))


def test_npz_with_time_and_controls(arrays):
    root, states, _ = arrays
    controls = np.random.default_rng(1).normal(size=(K, T, N, 1))
    np.savez(root / "s.npz", states=states, time=1.0 + 0.1 * np.arange(T))
    np.save(root / "u.npy", controls)
    out = root / "u.h5"
    result = invoke("import", "--states", root / "s.npz", "--adjacency", root / "a.npy", "--dt",
                    0.1, "--controls", root / "u.npy", "--control-names", "force", "--dtype",
                    "float64", "--out", out)
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    np.testing.assert_allclose(ds.time, 1.0 + 0.1 * np.arange(T), rtol=1e-12)
    np.testing.assert_array_equal(ds.controls, controls)
    assert ds.control_names == ("force",) and check_dataset(out).ok


def test_long_csv_in_any_row_order(arrays):
    root, states, _ = arrays
    rows = [(k, round(0.5 * t, 10), n, *states[k, t, n]) for k in range(K) for t in range(T)
            for n in range(N)]
    order = np.random.default_rng(2).permutation(len(rows))
    with open(root / "s.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["node", "v", "time", "w", "trajectory"])
        for i in order:
            k, t, n, v, w = rows[i]
            writer.writerow([n, repr(float(v)), t, repr(float(w)), k])
    out = root / "c.h5"
    result = invoke("import", "--states", root / "s.csv", "--adjacency", root / "a.npy", "--dt",
                    0.5, "--dtype", "float64", "--out", out)
    assert result.exit_code == 0, result.output
    ds = read_dataset(out)
    np.testing.assert_array_equal(ds.states, states)
    assert ds.state_names == ("v", "w")


def test_one_adjacency_per_trajectory(arrays):
    root, _, ring = arrays
    chain = np.zeros((N, N), dtype=np.uint8)
    for i in range(N - 1):
        chain[i, i + 1] = chain[i + 1, i] = 1
    per = np.stack([ring if k % 2 else chain for k in range(K)])  # two distinct graphs
    np.save(root / "per.npy", per)
    out = root / "per.h5"
    assert invoke("import", "--states", root / "s.npy", "--adjacency", root / "per.npy",
                  "--dt", 0.1, "--out", out).exit_code == 0
    ds = read_dataset(out)
    assert ds.num_graphs == 2
    np.testing.assert_array_equal(ds.adjacency[ds.graph_index], per)
    np.testing.assert_array_equal(TrajectoryData.load(out).adjacency.numpy(), per)


@pytest.mark.parametrize("directed", [False, True])
def test_edge_list_with_weights(arrays, directed):
    root, _, _ = arrays
    (root / "e.txt").write_text("# a chain 0-1-2, node 3 declared by a weight-0 edge\n"
                                "0 1 1\n1 2 1\n2 3 0\n")
    out = root / f"e{directed}.h5"
    args = ["--directed"] if directed else []
    assert invoke("import", "--states", root / "s.npy", "--edge-list", root / "e.txt", "--dt",
                  0.1, "--out", out, *args).exit_code == 0
    a = read_dataset(out).adjacency[0]
    expected = np.zeros((N, N), dtype=np.uint8)
    expected[1, 0] = expected[2, 1] = 1  # j sends to i: A[i, j]
    if not directed:
        expected = expected | expected.T
    np.testing.assert_array_equal(a, expected)
    assert read_dataset(out).config["topology"] == "edgelist"


def _bad(root, name, array):
    np.save(root / name, array)
    return root / name


@pytest.mark.parametrize("case", [
    "missing states", "3-d states", "nan", "text states", "adjacency of another N",
    "weighted adjacency", "adjacency and edge list", "no graph", "directed adjacency",
    "edge list of another N", "edge list gap", "csv without node column", "csv missing row",
    "csv duplicate row", "time off dt", "names count", "controls shape", "control names alone",
    "bad split", "negative dt", "exists", "out is a folder", "unknown suffix",
])
def test_bad_input_is_one_line_and_exit_2(arrays, case):
    root, states, ring = arrays
    args = {"--states": root / "s.npy", "--adjacency": root / "a.npy", "--dt": 0.1,
            "--out": root / "bad.h5"}
    extra: list = []
    if case == "missing states":
        args["--states"] = root / "nope.npy"
    elif case == "3-d states":
        args["--states"] = _bad(root, "s3.npy", states[0])
    elif case == "nan":
        s = states.copy()
        s[2, 3, 1, 0] = np.nan
        args["--states"] = _bad(root, "nan.npy", s)
    elif case == "text states":
        args["--states"] = _bad(root, "txt.npy", np.full((K, T, N, D), "a"))
    elif case == "adjacency of another N":
        args["--adjacency"] = _bad(root, "a5.npy", np.ones((5, 5)))
    elif case == "weighted adjacency":
        args["--adjacency"] = _bad(root, "aw.npy", ring * 0.5)
    elif case == "adjacency and edge list":
        (root / "e.txt").write_text("0 1\n1 2\n2 3\n")
        extra = ["--edge-list", root / "e.txt"]
    elif case == "no graph":
        del args["--adjacency"]
    elif case == "directed adjacency":
        extra = ["--directed"]
    elif case == "edge list of another N":
        del args["--adjacency"]
        (root / "e.txt").write_text("0 1\n")
        extra = ["--edge-list", root / "e.txt"]
    elif case == "edge list gap":
        del args["--adjacency"]
        (root / "e.txt").write_text("0 1\n1 3\n")
        extra = ["--edge-list", root / "e.txt"]
    elif case in ("csv without node column", "csv missing row", "csv duplicate row"):
        header = "trajectory,time,v" if case == "csv without node column" else \
            "trajectory,time,node,v"
        rows = [f"{k},{t},{n},1.0" for k in range(2) for t in range(3) for n in range(N)]
        rows = rows[:-1] if case == "csv missing row" else rows
        rows = rows + rows[:1] if case == "csv duplicate row" else rows
        (root / "s.csv").write_text("\n".join([header, *rows]) + "\n")
        args["--states"], args["--dt"] = root / "s.csv", 1.0
    elif case == "time off dt":
        np.savez(root / "t.npz", states=states, time=np.arange(T) * 0.2)
        args["--states"] = root / "t.npz"
    elif case == "names count":
        extra = ["--state-names", "a,b,c"]
    elif case == "controls shape":
        extra = ["--controls", _bad(root, "u.npy", np.zeros((K, T + 1, N, 1)))]
    elif case == "control names alone":
        extra = ["--control-names", "f"]
    elif case == "bad split":
        extra = ["--split", "0.5,0.6,0.1"]
    elif case == "negative dt":
        args["--dt"] = -0.1
    elif case == "exists":
        (root / "bad.h5").write_text("")
    elif case == "out is a folder":
        (root / "bad.h5").mkdir()
        extra = ["--force"]
    elif case == "unknown suffix":
        (root / "s.mat").write_bytes(b"")
        args["--states"] = root / "s.mat"
    result = invoke("import", *[x for kv in args.items() for x in kv], *extra)
    line = one_line_error(result)
    if case not in ("exists", "out is a folder"):
        assert not (root / "bad.h5").exists(), line
