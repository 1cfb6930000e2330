"""A pass over a dataset file holds one block of it, whatever the number of trajectories,
and an array whose header declares more than the file holds is refused before any read.

Once, `mpnode check`, `info` and `train --stream` held about 7 kB per trajectory (HDF5's
record of each chunk one read touches, a trajectory being one chunk): 2.2 GB for a file of
300,000 short trajectories. And a 24 kB file declaring 10⁷ trajectories, never written,
was read as fill values until the memory ran out.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
from conftest import child_env, guarded_cli

from mpnode_cli.data.reads import CHUNKS_PER_READ, block_rows


def _widened(src, out, k: int, *, write: int | None = None) -> None:
    """`src` with its per-trajectory arrays grown to `k` trajectories, one chunk each;
    only the first `write` rows (all where None) written."""
    shutil.copy(src, out)
    with h5py.File(out, "r+") as f:
        for name in ("states", "split", "graph_index", "solver/status", "solver/n_f_evals"):
            if name not in f:
                continue
            a = f[name][()]
            del f[name]
            d = f.create_dataset(name, shape=(k, *a.shape[1:]), dtype=a.dtype,
                                 chunks=(1, *a.shape[1:]))
            rows = k if write is None else write
            d[:rows] = np.resize(a, (rows, *a.shape[1:]))
        for key in ("fingerprint", "checksum"):
            f.attrs.pop(key, None)


def _peak_kib(*args) -> int:
    """The peak resident memory (KiB) of `mpnode check` on `args`, in a child of its own."""
    code = ("import resource, sys; from typer.testing import CliRunner; "
            "from mpnode_cli.cli.app import app; "
            "r = CliRunner().invoke(app, sys.argv[1:]); assert r.exit_code == 0, r.output; "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    done = subprocess.run([sys.executable, "-c", code, "check", *map(str, args)],
                          env=child_env(), capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return int(done.stdout.split()[-1])


def test_a_block_is_bounded_in_chunks_as_in_values():
    array = np.zeros((50_000, 11, 3, 3))
    assert block_rows(array, 10**6) == 10**6 // 99  # a numpy array: values alone

    class Chunked:  # an h5py dataset's shape and chunks
        shape, chunks = (50_000, 11, 3, 3), (1, 11, 3, 3)

    assert block_rows(Chunked, 10**6) == CHUNKS_PER_READ
    Chunked.chunks = (1, 11, 3, 1)  # three chunks across a row
    assert block_rows(Chunked, 10**6) == CHUNKS_PER_READ // 3


def test_check_holds_about_the_same_memory_for_30000_trajectories_as_for_6(user_files,
                                                                          tmp_path):
    big = tmp_path / "big.h5"
    _widened(user_files["data"], big, 30_000)
    small = _peak_kib(user_files["data"])
    grown = _peak_kib(big) - small
    # 7 kB a trajectory would be 205 MiB; the arrays themselves are 3.4 MiB.
    assert grown < 40 * 1024, (small, grown)


@pytest.mark.parametrize("verb", ["check", "info"])
def test_an_array_declared_larger_than_the_file_is_refused_in_one_line(user_files, tmp_path,
                                                                       verb):
    sparse = tmp_path / "sparse.h5"
    _widened(user_files["data"], sparse, 10**7, write=6)
    before = sparse.read_bytes()
    assert len(before) < 200_000
    (result,) = guarded_cli([verb, sparse], memory=2 * 2**30, timeout=60)
    assert result.exit_code == 2, result.output
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:"), result.output
    assert "declares shape [10000000" in lines[0] and "6 of its 10,000,000 chunks" in lines[0]
    assert sparse.read_bytes() == before


def _generate_peak_kib(out, k: int) -> int:
    code = ("import resource, sys; from typer.testing import CliRunner; "
            "from mpnode_cli.cli.app import app; "
            "r = CliRunner().invoke(app, sys.argv[1:]); assert r.exit_code == 0, r.output; "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    args = ["generate", "lorenz", "--nodes", "3", "--trajectories", str(k), "--t-end", "0.5",
            "--dt", "0.05", "--out", str(out), "-y"]
    done = subprocess.run([sys.executable, "-c", code, *args], env=child_env(),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    return int(done.stdout.split()[-1])


def test_generate_of_many_short_trajectories_stays_within_its_estimate(tmp_path):
    """Once 2.7× low: the write touched one HDF5 chunk per trajectory in one go."""
    from mpnode_cli.config.generate import GenerateConfig
    from mpnode_cli.data.generate import estimate

    k = 40_000
    grown = (_generate_peak_kib(tmp_path / "big.h5", k)
             - _generate_peak_kib(tmp_path / "small.h5", 16)) * 1024
    config = GenerateConfig(system="lorenz", nodes=3, trajectories=k, t_end=0.5, dt=0.05,
                            out=tmp_path / "x.h5")
    assert grown <= estimate(config).memory_bytes, (grown, estimate(config))
