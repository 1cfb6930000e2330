"""`mpnode generate --shard i/n` and `mpnode merge`: the shards merge into the single file.

The reference is always an unsharded `generate` of the same config, read back with h5py.
"""

from __future__ import annotations

import json
import os

import h5py
import numpy as np
import pytest
from typer.testing import CliRunner

from mpnode_cli.cli.app import app
from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data import shards as shards_module
from mpnode_cli.data.generate import generate
from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.data.shards import shard_path, shard_range
from mpnode_cli.data.validate import check_dataset

runner = CliRunner()
# Gene on two graphs: 11 trajectories in chunks of 2 (6 chunks of 2, 2, 2, 2, 2, 1).
FIELDS = {"system": "gene", "grid": 2, "topology": "er", "graphs": 2, "trajectories": 11,
          "t_end": 0.5, "dt": 0.1, "chunk_size": 2}
PROVENANCE = {"created_utc", "merged", "checksum"}  # the checksum covers created_utc


def contents(path) -> tuple[dict, dict]:
    """Every dataset of a file (as numpy arrays, with dtype) and its attributes, root and
    group attributes alike, apart from provenance."""
    arrays, attrs = {}, {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                arrays[name] = obj[()]
            attrs.update({f"{name}@{k}": v for k, v in obj.attrs.items()})

        f.visititems(visit)
        attrs.update({k: v for k, v in f.attrs.items() if k not in PROVENANCE})
    attrs["config"] = json.loads(attrs["config"])
    return arrays, attrs


def assert_same_file(path, reference):
    arrays, attrs = contents(path)
    want_arrays, want_attrs = contents(reference)
    assert sorted(arrays) == sorted(want_arrays)
    for name, want in want_arrays.items():
        assert arrays[name].dtype == want.dtype, name
        assert arrays[name].tobytes() == want.tobytes(), name  # bit for bit
    assert attrs.keys() == want_attrs.keys()
    for key, want in want_attrs.items():
        assert np.array_equal(attrs[key], want) if isinstance(want, np.ndarray) else (
            attrs[key] == want), key


def shard_files(count: int, **fields) -> list:
    return [generate(GenerateConfig(**(FIELDS | fields), out="sharded.h5",
                                    shard=(i, count))).path for i in range(count)]


@pytest.fixture
def single(tmp_path, monkeypatch):
    """The unsharded file `single/d.h5`; tests then work in `tmp_path` itself, so that a
    merge to `d.h5` records the same relative `out` as the single file."""
    (tmp_path / "single").mkdir()
    monkeypatch.chdir(tmp_path / "single")
    generate(GenerateConfig(**FIELDS, out="d.h5"))
    monkeypatch.chdir(tmp_path)
    return tmp_path / "single" / "d.h5"


@pytest.mark.parametrize("count", [1, 2, 3])
def test_shard_then_merge_equals_the_single_file(single, count):
    paths = shard_files(count)
    result = runner.invoke(app, ["merge", *map(str, reversed(paths)), "-o", "d.h5"])
    assert result.exit_code == 0, result.output
    assert_same_file("d.h5", single)
    merged = json.loads(h5py.File("d.h5", "r").attrs["merged"])
    assert merged["shards"] == [p.name for p in paths] and merged["redrawn"] == 0


def test_each_shard_is_a_dataset_of_its_slice(single):
    whole = read_dataset(single)
    for i, path in enumerate(shard_files(3)):
        assert path.name == f"sharded.shard-{i:04d}-of-0003.h5"
        start, stop = shard_range(11, 2, i, 3)
        assert check_dataset(path).ok
        part = read_dataset(path)
        assert part.states.tobytes() == whole.states[start:stop].tobytes()
        np.testing.assert_array_equal(part.split, whole.split[start:stop])
        np.testing.assert_array_equal(part.graph_index, whole.graph_index[start:stop])
        np.testing.assert_array_equal(part.adjacency, whole.adjacency)  # all G graphs
        assert part.config["shard"] == [i, 3]
        info = json.loads(part.extra_attrs["shard"])
        assert info == {"index": i, "count": 3, "start": start, "stop": stop,
                        "trajectories": 11, "redraw_seed": [0, 2, i, 3]}
    # Whole chunks of 2: shards of 2, 2 and 1 chunks.
    assert [shard_range(11, 2, i, 3) for i in range(3)] == [(0, 4), (4, 8), (8, 11)]
    assert "shard" not in whole.config  # a single file's config reads as before shards


def test_virtual_merge_reads_the_shards_and_refuses_a_missing_one(single, tmp_path):
    paths = shard_files(2)
    result = runner.invoke(app, ["merge", *map(str, paths), "-o", "d.h5", "--virtual"])
    assert result.exit_code == 0, result.output
    assert_same_file("d.h5", single)
    with h5py.File("d.h5", "r") as f:
        assert f["states"].is_virtual
    os.chdir(tmp_path / "single")  # the shards are found relative to the file, not here
    assert check_dataset(tmp_path / "d.h5").ok
    os.chdir(tmp_path)
    paths[1].rename(tmp_path / "elsewhere.h5")
    report = check_dataset("d.h5")
    assert not report.ok and paths[1].name in report.problems[0]


def test_shards_that_had_redraws_are_deterministic_and_say_so(tmp_path, monkeypatch):
    # The appendix's wide box makes about one pendulum in five singular: redrawn.
    monkeypatch.chdir(tmp_path)
    fields = {"system": "pendulum", "nodes": 2, "trajectories": 16, "t_end": 2.0,
              "params": {"ic_range": "paper"}, "chunk_size": 4}
    single = read_dataset(generate(GenerateConfig(**fields, out="one.h5")).path)
    paths = [generate(GenerateConfig(**fields, out="p.h5", shard=(i, 2))).path
             for i in range(2)]
    again = generate(GenerateConfig(**fields, out="again.h5", shard=(1, 2))).path
    assert read_dataset(again).states.tobytes() == read_dataset(paths[1]).states.tobytes()
    redrawn = sum(read_dataset(p).extra_attrs["n_rejected"] + read_dataset(p).extra_attrs[
        "n_failed"] for p in paths)
    assert redrawn > 0
    result = runner.invoke(app, ["merge", *map(str, paths), "-o", "m.h5"])
    assert result.exit_code == 0 and f"redrew {redrawn} trajectories" in result.output
    merged = read_dataset("m.h5")
    np.testing.assert_array_equal(merged.split, single.split)  # its own generator
    assert merged.extra_attrs["n_rejected"] + merged.extra_attrs["n_failed"] == redrawn
    assert np.isfinite(merged.states).all() and (merged.solver_status == 0).all()


def one_line_error(result) -> str:
    assert result.exit_code == 2, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), lines
    return lines[0]


@pytest.mark.parametrize(("spec", "message"), [
    ("3/2", "0 ≤ i < n"), ("0/0", "0 ≤ i < n"), ("x", "got 'x'"), ("1/2/3", "i/n"),
    ("0/7", "there are only 6"),
])
def test_bad_shard_spec_is_one_line_and_exit_2(tmp_path, monkeypatch, spec, message):
    monkeypatch.chdir(tmp_path)
    args = ["generate", "gene", "--grid", "2", "--trajectories", "11", "--t-end", "0.5",
            "--dt", "0.1", "--chunk-size", "2", "--shard", spec, "-o", "d.h5"]
    assert message in one_line_error(runner.invoke(app, args))
    assert list(tmp_path.iterdir()) == []


def test_merge_refuses_shards_that_do_not_belong_together(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    paths = shard_files(3)
    other = generate(GenerateConfig(**FIELDS, seed=1, out="other.h5", shard=(2, 3))).path
    halves = shard_files(2, trajectories=12)
    single = generate(GenerateConfig(**FIELDS, out="single.h5")).path

    def merge(*files):
        return one_line_error(runner.invoke(app, ["merge", *map(str, files), "-o", "m.h5"]))

    assert "missing (index 1)" in merge(paths[0], paths[2])
    assert "given twice" in merge(paths[0], paths[1], paths[1], paths[2])
    assert "configs differ in 'seed'" in merge(paths[0], paths[1], other)
    assert "configs differ in 'trajectories'" in merge(paths[0], paths[1], halves[1])
    assert "not a shard" in merge(paths[0], single)
    assert "no such shard file" in merge(paths[0], "nope.h5")
    assert "is one of the inputs" in one_line_error(runner.invoke(
        app, ["merge", *map(str, paths), "-o", str(paths[0]), "--force"]))
    assert not (tmp_path / "m.h5").exists()


def test_merge_checks_its_shards_first(tmp_path, monkeypatch):
    """A shard that the dataset check refuses (a NaN here) is refused by merge, naming it,
    before anything is written."""
    monkeypatch.chdir(tmp_path)
    paths = shard_files(2)
    with h5py.File(paths[1], "r+") as f:
        f["states"][0, 1, 0, 0] = np.nan
    result = runner.invoke(app, ["merge", *map(str, paths), "-o", "m.h5"])
    assert result.exit_code == 2 and "Traceback" not in result.output
    assert str(paths[1]) in result.output and "non-finite" in result.output
    assert not (tmp_path / "m.h5").exists()


def test_interrupted_merge_leaves_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    paths = shard_files(2)
    before = sorted(tmp_path.iterdir())

    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(shards_module, "_copy", interrupted)
    result = runner.invoke(app, ["merge", *map(str, paths), "-o", "m.h5"])
    assert result.exit_code == 130 and "nothing written to m.h5" in result.stderr
    assert sorted(tmp_path.iterdir()) == before  # no merged file, no temporary


def test_merge_copies_in_bounded_blocks(single, monkeypatch):
    """A block of one trajectory at a time gives the same file (the copy, the shards'
    check and the checksum never need the whole array)."""
    from mpnode_cli.data import integrity, validate

    for module in (shards_module, integrity, validate):
        monkeypatch.setattr(module, "_BLOCK_VALUES" if module is not validate else
                            "BLOCK_VALUES", 1)
    reads = []
    original = h5py.Dataset.__getitem__

    def spy(self, key):
        value = original(self, key)
        if self.name == "/states" and isinstance(key, slice):
            reads.append(len(value))
        return value

    monkeypatch.setattr(h5py.Dataset, "__getitem__", spy)
    paths = shard_files(2)
    reads.clear()
    shards_module.merge_shards(paths, "d.h5")
    monkeypatch.setattr(h5py.Dataset, "__getitem__", original)
    assert reads and max(reads) == 1
    assert_same_file("d.h5", single)


def test_shard_path_names():
    assert shard_path("datasets/x.h5", 3, 8).as_posix() == "datasets/x.shard-0003-of-0008.h5"
    assert shard_path("x", 0, 2).as_posix() == "x.shard-0000-of-0002.h5"
