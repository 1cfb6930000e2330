"""What `mpnode check` passes, `info` reads; what it refuses, no writer writes.

Once, a file whose `states` was a soft link to another array passed `check`, then `info`
failed with a KeyError; an object name that is not UTF-8 (a flipped byte) passed `check`,
then `info` failed with a TypeError; and repeated state names passed `check`.
"""

from __future__ import annotations

import dataclasses
import shutil

import h5py
import numpy as np
import pytest
from conftest import invoke, one_line_error

from mpnode_cli.data.hdf5 import read_dataset
from mpnode_cli.data.hdf5_write import write_dataset


def _copy(user_files, tmp_path):
    path = tmp_path / "d.h5"
    shutil.copy(user_files["data"], path)
    return path


def test_info_reads_an_array_behind_a_soft_link(user_files, tmp_path):
    path = _copy(user_files, tmp_path)
    with h5py.File(path, "r+") as f:
        states = f["states"][()]
        del f["states"]
        f.create_dataset("real", data=states)
        f["states"] = h5py.SoftLink("/real")
    assert invoke("check", path).exit_code == 0
    result = invoke("info", path, "--json")
    assert result.exit_code == 0, result.output
    assert '"trajectories": 6' in result.output.replace("\n", " ").replace("  ", " ")


def test_an_object_name_that_is_not_text_is_refused_by_check_and_info(user_files, tmp_path):
    path = _copy(user_files, tmp_path)
    with h5py.File(path, "r+") as f:
        f.create_group(b"params\xa5").create_dataset("coupling", data=[1.0])
    before = path.read_bytes()
    for verb in ("check", "info"):
        line = one_line_error(invoke(verb, path))
        assert "not text" in line and "params" in line, line
    assert path.read_bytes() == before


def test_check_refuses_repeated_state_names_of_an_older_file(user_files, tmp_path):
    path = _copy(user_files, tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["state_names"] = '["p", "p"]'
    before = path.read_bytes()
    line = one_line_error(invoke("check", path))
    assert "state_names ['p', 'p'] repeats 'p'" in line, line
    assert path.read_bytes() == before


def test_no_writer_writes_repeated_state_names(user_files, tmp_path):
    ds = dataclasses.replace(read_dataset(user_files["data"]), state_names=("p", "p"))
    with pytest.raises(ValueError, match=r"state names \['p', 'p'\] repeat a name"):
        write_dataset(tmp_path / "out.h5", ds)
    assert not list(tmp_path.iterdir())


def test_import_refuses_repeated_columns(tmp_path):
    rows = ["trajectory,time,node,p,p"]
    g = np.random.default_rng(0)
    rows += [f"{k},{t * 0.1:.1f},{n},{g.normal():.6f},{g.normal():.6f}"
             for k in range(4) for t in range(5) for n in range(3)]
    (tmp_path / "s.csv").write_text("\n".join(rows) + "\n")
    (tmp_path / "ring.txt").write_text("0 1\n1 2\n2 0\n")
    out = tmp_path / "b.h5"
    one_line_error(invoke("import", "--states", tmp_path / "s.csv", "--edge-list",
                          tmp_path / "ring.txt", "--dt", 0.1, "--out", out))
    assert not out.exists()


def test_a_system_name_with_a_direction_mark_is_refused_escaped(user_files, tmp_path):
    path = _copy(user_files, tmp_path)
    with h5py.File(path, "r+") as f:
        f.attrs["system"] = "lor\u202eenz"
    line = one_line_error(invoke("check", path))
    assert "attribute system 'lor\\u202eenz' holds characters that are not printable" in line
    assert "\u202e" not in line
