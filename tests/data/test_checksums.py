"""Files that carry checksums (`mpnode_cli.data.integrity`, `training/checkpoint_digest.py`).

A dataset's arrays carry HDF5's Fletcher-32 on every chunk and the file the sha256 of its
contents; a checkpoint the sha256 of its fields. A changed byte used to read as another
number: a value in `states` or in a weight passed `mpnode check` and trained on. Now it is
one line naming the file (and the array) for every reader, exit 2, and files written before
checksums still read, `check` saying they carry none. Damaged HDF5 bookkeeping is one line
too, where it was a traceback from `check`, `info`, `train` and `evaluate`.
"""

from __future__ import annotations

import shutil

import h5py
import numpy as np
import pytest
import torch
from conftest import invoke, one_line_error

from mpnode_cli.data.hdf5 import DatasetFormatError, read_dataset
from mpnode_cli.data.validate import check_dataset


@pytest.fixture
def data(tiny_checkpoint, tmp_path):
    """A copy of the tiny checkpoint's dataset (8 Lorenz trajectories of 3 nodes)."""
    path = tmp_path / "l3.h5"
    shutil.copy(tiny_checkpoint.parents[2] / "l3.h5", path)
    return path


def flip_in(path, array: str, chunk: int = 0) -> None:
    """Change one byte of `array`'s values, inside its chunk `chunk`."""
    with h5py.File(path, "r") as f:
        at = f[array].id.get_chunk_info(chunk).byte_offset + 1
    raw = bytearray(path.read_bytes())
    raw[at] ^= 0x5A
    path.write_bytes(bytes(raw))


def readers(path, run):
    return {"check": ["check", path], "info": ["info", path],
            "train": ["train", path, "--epochs", 1, "--run-dir", path.parent / "r2"],
            "evaluate": ["evaluate", run, path]}


@pytest.mark.parametrize("verb", ["check", "info", "train", "evaluate"])
def test_a_changed_value_fails_its_checksum_in_every_reader(data, tiny_checkpoint, verb):
    flip_in(data, "states", chunk=3)
    line = one_line_error(invoke(*readers(data, tiny_checkpoint)[verb]))
    assert str(data) in line and "array states is damaged" in line, line
    assert not (data.parent / "r2").exists()


def test_an_array_check_does_not_read_is_found_by_deep_and_named_by_readers(data):
    """`solver/status` is not read by a plain check; `check --deep` reads every byte, and
    a reader that meets it names it."""
    flip_in(data, "solver/status")
    assert check_dataset(data).ok
    line = one_line_error(invoke("check", "--deep", data))
    assert "array solver/status is damaged" in line
    with pytest.raises(DatasetFormatError, match=r"l3\.h5: array solver/status is damaged"):
        read_dataset(data)


def test_a_changed_attribute_is_found_by_deep(data):
    """Attributes carry no Fletcher-32: the contents' sha256 covers them."""
    with h5py.File(data, "r+") as f:
        f.attrs["dt"] = 0.0500001  # within check's slack against `time`
    assert check_dataset(data).ok
    line = one_line_error(invoke("check", "--deep", data))
    assert "contents are not those written" in line


def test_the_checksums_are_verified_and_said(data):
    result = invoke("check", "--deep", data)
    assert result.exit_code == 0, result.output
    assert "checksums: verified: Fletcher-32 on each array, sha256 of the" in result.output
    assert "check --deep verifies" in invoke("check", data).output


def test_a_file_from_before_checksums_reads_and_says_it_has_none(data, tmp_path):
    old = tmp_path / "old.h5"
    with h5py.File(data, "r") as src, h5py.File(old, "w") as dst:
        dst.attrs.update({k: v for k, v in src.attrs.items() if k != "checksum"})
        for name in ("time", "states", "graph/edges", "graph/num_edges", "graph/adjacency",
                     "graph_index", "split", "solver/status", "solver/n_f_evals"):
            dst[name] = src[name][()]  # contiguous, unfiltered: as mpnode wrote them
        dst.require_group("params").attrs.update(src["params"].attrs)
    result = invoke("check", "--deep", old)
    assert result.exit_code == 0, result.output
    assert "checksums: none (written before mpnode recorded them" in result.output
    np.testing.assert_array_equal(read_dataset(old).states, read_dataset(data).states)


@pytest.mark.parametrize("verb", ["check", "info", "train", "evaluate"])
def test_damaged_hdf5_bookkeeping_is_one_line(data, tiny_checkpoint, verb):
    """The audit's repro: 4096 bytes zeroed a third of the way in."""
    raw = bytearray(data.read_bytes())
    third = len(raw) // 3
    raw[third:third + 4096] = bytes(len(raw[third:third + 4096]))
    data.write_bytes(bytes(raw))
    line = one_line_error(invoke(*readers(data, tiny_checkpoint)[verb]))
    assert str(data) in line and "damaged" in line, line


def flip_weight(path) -> None:
    """Change one byte inside the first weight tensor's stored values."""
    payload = torch.load(path, weights_only=True)
    first = next(iter(payload["state_dict"].values()))
    raw = bytearray(path.read_bytes())
    at = raw.find(first.numpy().tobytes()[:16]) + 3
    assert at > 3
    raw[at] ^= 0x5A
    path.write_bytes(bytes(raw))


def test_a_changed_weight_is_refused_by_check_resume_and_evaluate(own_user_files):
    run = own_user_files["run"]
    for name in ("last", "best"):
        flip_weight(run / "checkpoints" / f"{name}.pt")
    for args in (["check", run / "checkpoints" / "last.pt"],
                 ["train", "--resume", run, "--epochs", 3],
                 ["evaluate", run, own_user_files["data"]]):
        line = one_line_error(invoke(*args))
        assert ".pt is damaged: its contents are not those it was saved with" in line


def test_a_checkpoint_from_before_digests_loads_and_says_it_has_none(user_files, tmp_path):
    payload = torch.load(user_files["checkpoint"], weights_only=True)
    assert len(payload.pop("payload_sha256")) == 64
    torch.save(payload, tmp_path / "old.pt")
    result = invoke("check", tmp_path / "old.pt")
    assert result.exit_code == 0, result.output
    assert "checksum: none (saved before mpnode recorded one)" in result.output
    assert "checksum: sha256 of the contents, verified" in invoke(
        "check", user_files["checkpoint"]).output
