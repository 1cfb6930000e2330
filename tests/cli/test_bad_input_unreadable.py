"""Unreadable inputs: every file a verb cannot read is one `Error:` line that names it, exit 2,
with no warning before it and no advice to unpickle.

Once: an empty `.npy` gave "Aborted." and exit 1; a text file named `.npy` passed on
numpy's hint to load it with `allow_pickle`, which invites running a pickle's code; a
binary edge list gave a bare `'utf-8' codec` error without the file's name; a CSV with a
header and no rows leaked numpy's warning; a raw pickle named `.pt` leaked torch's
two-line warning before the error; a damaged run folder gave a bare JSON or `utf-8` error.
"""

from __future__ import annotations

import io
import pickle
import warnings
import zipfile

import numpy as np
import pytest
from conftest import one_line_error
from typer.testing import CliRunner

from mpnode_cli.cli.app import app

runner = CliRunner()
BINARY = bytes(range(128, 256)) * 4 + b"\x00\x01 \n"


def invoke(*args):
    """The CLI's result, and the warnings raised while it ran (pytest would hide them)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = runner.invoke(app, [str(a) for a in args])
    return result, [str(w.message) for w in caught]


def refused(*args, names: str) -> str:
    """The one error line of a refused command, which names `names` and warned nothing."""
    result, caught = invoke(*args)
    line = one_line_error(result)
    assert names in line and not caught, (line, caught)
    assert "Aborted" not in result.output
    assert "allow_pickle" not in result.output and "pickle.load" not in result.output, line
    return line


def npy_header(shape: tuple[int, ...], descr: str = "<f8") -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": descr, "fortran_order": False,
                                                  "shape": shape})
    return buffer.getvalue()


def _objects(path):
    np.save(path, np.array([{"a": 1}, None], dtype=object), allow_pickle=True)


def _truncated(path):
    np.save(path, np.zeros((2, 3, 3)))
    path.write_bytes(path.read_bytes()[:-20])


def _npz_of_objects(path):
    with zipfile.ZipFile(path, "w") as archive:
        buffer = io.BytesIO()
        np.save(buffer, np.array([{"a": 1}], dtype=object), allow_pickle=True)
        archive.writestr("states.npy", buffer.getvalue())


def _npz_forged(path):
    with zipfile.ZipFile(path, "w") as archive:  # declares 24 TB, holds 64 bytes
        archive.writestr("states.npy", npy_header((10**6, 10**6, 3)) + bytes(64))


# Each file, and the words its one line must hold.
ARRAYS = {
    "empty.npy": (lambda p: p.write_bytes(b""), "is empty"),
    "text.npy": (lambda p: p.write_text("1 2 3\n4 5 6\n"), "is not numpy data"),
    "pickle.npy": (lambda p: p.write_bytes(pickle.dumps([1.0, 2.0])), "is not numpy data"),
    "objects.npy": (_objects, "holds Python objects"),
    "truncated.npy": (_truncated, "is truncated"),
    "forged.npy": (lambda p: p.write_bytes(npy_header((10**6, 10**6, 3)) + bytes(64)),
                   "is truncated"),
    "header.npy": (lambda p: p.write_bytes(b"\x93NUMPY\x01\x00\x10\x00{'descr': nonsense"),
                   "not a .npy header"),
    "objects.npz": (_npz_of_objects, "holds Python objects"),
    "forged.npz": (_npz_forged, "is truncated"),
    "damaged.npz": (lambda p: p.write_bytes(b"PK\x03\x04" + bytes(40)), "damaged zip"),
}


@pytest.mark.parametrize("name", list(ARRAYS))
def test_an_unreadable_array_is_one_line_naming_it(tmp_path, tiny_checkpoint, name):
    make, words = ARRAYS[name]
    bad = tmp_path / name
    make(bad)
    edges = tmp_path / "g.txt"
    edges.write_text("0 1\n1 2\n")
    good = tmp_path / "x0.npy"
    np.save(good, np.zeros((2, 3, 3)))
    out = tmp_path / "out.h5"
    for args in (["import", "--states", bad, "--edge-list", edges, "--dt", 0.1],
                 ["import", "--states", tmp_path / "s.npy", "--adjacency", bad, "--dt", 0.1],
                 ["simulate", tiny_checkpoint, "--x0", bad, "--edge-list", edges,
                  "--t-end", 0.2, "--dt", 0.1],
                 ["simulate", tiny_checkpoint, "--x0", good, "--edge-list", edges,
                  "--controls", bad, "--t-end", 0.2, "--dt", 0.1]):
        np.save(tmp_path / "s.npy", np.zeros((2, 3, 3, 1)))
        assert words in refused(*args, "--out", out, names=name)
    assert not out.exists()


@pytest.mark.parametrize(("content", "words"), [
    (BINARY, "is not UTF-8 text"),
    (b"0 1\n" + bytes(5000), "is not UTF-8 text"),  # NUL bytes decode, but are no text
    (b"0 " + b"1" * 10000, "a line of more than"),
])
def test_a_binary_edge_list_is_one_line_naming_it(tmp_path, tiny_checkpoint, content, words):
    edges = tmp_path / "graph.bin"
    edges.write_bytes(content)
    states, x0 = tmp_path / "s.npy", tmp_path / "x0.npy"
    np.save(states, np.zeros((2, 3, 3, 1)))
    np.save(x0, np.zeros((2, 3, 3)))
    out = tmp_path / "out.h5"
    for args in (["import", "--states", states, "--edge-list", edges, "--dt", 0.1],
                 ["generate", "kuramoto", "--edge-list", edges, "--trajectories", 2],
                 ["simulate", tiny_checkpoint, "--x0", x0, "--edge-list", edges,
                  "--t-end", 0.2, "--dt", 0.1]):
        assert words in refused(*args, "--out", out, names="graph.bin")
    assert not out.exists()


@pytest.mark.parametrize(("content", "words"), [
    (b"trajectory,time,node,x\n", "has a header but no rows"),
    (b"trajectory,time,node,x\n0,0,0\n0,1,0\n", "every row must hold 4 numbers"),
    (b"trajectory,time,node,x\n0,0,0,1\n" + BINARY, "is not UTF-8 text"),
    (BINARY, "is not UTF-8 text"),
])
def test_an_unreadable_csv_is_one_line_without_warnings(tmp_path, content, words):
    table = tmp_path / "long.csv"
    table.write_bytes(content)
    edges = tmp_path / "g.txt"
    edges.write_text("0 1\n")
    out = tmp_path / "out.h5"
    assert words in refused("import", "--states", table, "--edge-list", edges, "--dt", 1,
                            "--out", out, names="long.csv")
    assert not out.exists()


def test_a_raw_pickle_named_pt_is_one_line_without_torchs_warning(tmp_path):
    fake = tmp_path / "model.pt"
    fake.write_bytes(pickle.dumps({"state_dict": [1, 2, 3]}, protocol=4))
    data = tmp_path / "x0.npy"
    np.save(data, np.zeros((1, 3, 3)))
    for args in (["evaluate", fake, data],
                 ["simulate", fake, "--x0", data, "--adjacency", tmp_path / "a.npy",
                  "--t-end", 0.2, "--dt", 0.1, "--out", tmp_path / "p.h5"]):
        assert "not an mpnode checkpoint" in refused(*args, names="model.pt")


def test_a_binary_config_or_experiment_is_one_line_naming_it(tmp_path):
    for name in ("config.toml", "spec.toml"):
        (tmp_path / name).write_bytes(BINARY)
    assert "is not UTF-8 text" in refused("generate", "lorenz", "--config",
                                          tmp_path / "config.toml", names="config.toml")
    assert "is not UTF-8 text" in refused("experiment", "run", tmp_path / "spec.toml",
                                          names="spec.toml")


@pytest.mark.parametrize(("name", "content", "words"), [
    ("config.json", BINARY, "config.json is not UTF-8 text"),
    ("config.json", b'{"model": ', "config.json is not valid JSON (line 1"),
    ("config.json", b"[1, 2]", "config.json holds no JSON object"),
    ("metrics.jsonl", b'{"epoch": 0}\n{"epoch": 1, "val_lo', "metrics.jsonl:2 is not a row"),
])
def test_a_damaged_run_folder_is_one_line_naming_its_file(tmp_path, tiny_checkpoint, name,
                                                          content, words):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(tiny_checkpoint.parent.parent, run)
    (run / "summary.json").unlink()  # compare then reads the config and the metrics
    (run / name).write_bytes(content)
    assert words in refused("compare", run, names=name)
    assert words in refused("train", "--resume", run, "--epochs", 3, names=name)
