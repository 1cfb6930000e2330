"""A virtual merge (`mpnode merge --virtual`) whose shard is gone says which shard.

HDF5 reads a virtual dataset's missing source as the fill value without a word, so a shard
moved or deleted after the merge used to be reported as a bad `graph_index` or as NaN
values. Now `check` and every reader (`info`, `train`, `train --stream`, `evaluate`, the
Python readers) name the shard file and where it belongs.
"""

from __future__ import annotations

import os
import shutil

import pytest
from conftest import invoke, one_line_error

from mpnode_cli.config.generate import GenerateConfig
from mpnode_cli.data.dataset import TrajectoryData
from mpnode_cli.data.generate import generate
from mpnode_cli.data.hdf5 import DatasetFormatError, read_dataset

FIELDS = {"system": "gene", "grid": 2, "topology": "er", "trajectories": 16, "t_end": 0.3,
          "dt": 0.1, "chunk_size": 4}


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """Two shards, their virtual merge, and a 1-epoch run trained on it: kept pristine and
    copied for each test (`merged`)."""
    root = tmp_path_factory.mktemp("virtual")
    shards = [generate(GenerateConfig(**FIELDS, out=root / "g.h5", shard=(i, 2))).path
              for i in range(2)]
    result = invoke("merge", *shards, "-o", root / "g.h5", "--virtual")
    assert result.exit_code == 0, result.output
    result = invoke("train", root / "g.h5", "--epochs", 1, "--batch-size", 8, "--no-plots",
                    "--run-dir", root / "run")
    assert result.exit_code == 0, result.output
    return root


@pytest.fixture
def merged(built, tmp_path):
    """A fresh copy of the folder (merged file, shards, run): tests may break it."""
    folder = tmp_path / "data"
    shutil.copytree(built, folder)
    return folder


def readers(folder):
    """Each verb that reads the merged file, as CLI arguments."""
    data = folder / "g.h5"
    return {"check": ["check", data], "info": ["info", data],
            "train": ["train", data, "--epochs", 1, "--run-dir", folder / "r2"],
            "stream": ["train", data, "--stream", "--epochs", 1, "--run-dir", folder / "r3"],
            "evaluate": ["evaluate", folder / "run", data]}


SHARD = "g.shard-0001-of-0002.h5"


@pytest.mark.parametrize("verb", ["check", "info", "train", "stream", "evaluate"])
@pytest.mark.parametrize("how", ["deleted", "moved"])
def test_every_reader_names_the_missing_shard(merged, verb, how):
    if how == "deleted":
        (merged / SHARD).unlink()
    else:
        (merged / "elsewhere").mkdir()
        (merged / SHARD).rename(merged / "elsewhere" / SHARD)
    line = one_line_error(invoke(*readers(merged)[verb]))
    assert SHARD in line and "missing" in line and str(merged / SHARD) in line
    assert "graph_index" not in line and "NaN" not in line and "finite" not in line
    assert not (merged / "r2").exists() and not (merged / "r3").exists()


def test_the_merged_file_moved_without_its_shards(merged, tmp_path):
    away = tmp_path / "away"
    away.mkdir()
    shutil.move(merged / "g.h5", away / "g.h5")
    line = one_line_error(invoke("check", away / "g.h5"))
    assert "2 of its 2 shards" in line and str(away / "g.shard-0000-of-0002.h5") in line
    # Put back beside it, the shards are found again, from any working directory.
    for name in ("g.shard-0000-of-0002.h5", SHARD):
        shutil.copy(merged / name, away / name)
    os.chdir(tmp_path)
    assert invoke("check", away / "g.h5").exit_code == 0


def test_a_shard_replaced_by_another_file(merged):
    other = generate(GenerateConfig(**{**FIELDS, "trajectories": 4, "chunk_size": 4},
                                    out=merged / "small.h5")).path
    shutil.copy(other, merged / SHARD)
    line = one_line_error(invoke("check", merged / "g.h5"))
    assert SHARD in line and "replaced" in line


def test_the_python_readers_name_the_shard(merged):
    (merged / SHARD).unlink()
    for read in (read_dataset, TrajectoryData.load):
        with pytest.raises(DatasetFormatError, match=SHARD):
            read(merged / "g.h5")


@pytest.mark.parametrize("verb", ["check", "train", "evaluate"])
def test_a_shard_replaced_by_one_of_another_dataset_is_refused(merged, verb):
    """Regenerated with another seed, the shard holds the same arrays at the same shapes,
    so HDF5 and the shapes cannot tell; the checksum the merge recorded of it can."""
    config = GenerateConfig(**FIELDS, seed=7, out=merged / "g.h5", shard=(1, 2))
    generate(config, overwrite=True)
    line = one_line_error(invoke(*readers(merged)[verb]))
    assert SHARD in line and "not the file it merged" in line and "merge" in line
    assert not (merged / "r2").exists()


def test_a_shard_copied_elsewhere_with_its_merge_still_reads(merged, tmp_path):
    """A copy (new modification times) is still the file it merged."""
    shutil.copytree(merged, tmp_path / "copy", copy_function=shutil.copy)
    assert invoke("check", tmp_path / "copy" / "g.h5").exit_code == 0
